"""The pytest plugin (entry point ``pytest11: felis``): fixtures for sim-in-the-loop tests.

Fixtures cannot take call arguments, so the ones that build something are factories (pytest's "factory as
fixture" pattern): the fixture gives a function, the test calls it with the arguments it wants, as often as it
wants, and everything built is closed when the test ends, whatever way it ends::

    def test_cat_stands(sim_robot, run):
        res = run(sim_robot("cat"), "stand", 1.0)
        assert_joint_within(res, "spine_pitch", -0.05, 0.05, t=(0.5, None))

==============  ===========================================================================================
``sim_robot``   ``sim_robot(robot="cat", *, drop=None, **options)``: a connected MuJoCo robot
                (`felis.testing.resources.open_sim_robot`)
``virtual_bus`` ``virtual_bus(robot="cat", *, faults=None, sim=False, process=False, …)``: a running virtual
                Dynamixel bus, as a `VirtualPort` (``.port``, ``.bus``; `open_virtual_bus`)
``dxl_robot``   ``dxl_robot(vb, robot=None, **options)``: a connected `DynamixelRobot` on that port through the
                unmodified dynamixel-sdk (`open_dxl_robot`)
``run``         ``run(robot, controller, seconds, *, log=True, rate=None, …)``: one run with its MCAP log in the
                test's ``tmp_path``, read back (`felis.testing.runner.run_controller`; a `RunResult`)
``felis_stack`` the `contextlib.ExitStack` the factories open on; closed last-opened-first at the test's end
==============  ===========================================================================================

All of a test's robots and buses share one stack, so a servo robot is closed (torque off, read back) before the
bus it talks to stops. This module imports pytest and nothing heavy: MuJoCo, the SDK and the Foxglove SDK load
inside the factories, so a pytest run whose tests never ask for them pays nothing for the plugin but the
``felis`` package itself (numpy). ``pytest -p no:felis`` switches the plugin off.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest


@pytest.fixture
def felis_stack():
    """The ExitStack every felis factory fixture of this test opens on; closed (last opened, first closed) at the
    end of the test, on every path: robots closed with torque off, buses stopped, child processes ended."""
    with contextlib.ExitStack() as stack:
        yield stack


@pytest.fixture
def sim_robot(felis_stack):
    """Factory: ``sim_robot(robot="cat", *, drop=None, **options)`` → a connected `felis.sim.MujocoRobot`
    (``drop``: a height in m or (height, roll°, pitch°, yaw°); ``options``: MujocoRobot's, e.g. ``fixed_base``).
    Closed at the end of the test."""
    from felis.testing.resources import open_sim_robot

    def make(robot="cat", **options):
        return open_sim_robot(felis_stack, robot, **options)

    return make


@pytest.fixture
def virtual_bus(felis_stack):
    """Factory: ``virtual_bus(robot="cat", *, faults=None, sim=False, process=False, baud=1000000, seed=0, …)``
    → a running virtual Dynamixel bus (`felis.testing.resources.VirtualPort`: ``.port`` to open, ``.bus`` to
    inject faults while a run goes on). ``faults``: spec text such as ``"drop=0.01,hwerror=6:overload"``;
    ``sim=True``: servos backed by MuJoCo; ``process=True``: served from a child process. Stopped at the end of
    the test."""
    from felis.testing.resources import open_virtual_bus

    def make(robot="cat", **options):
        return open_virtual_bus(felis_stack, robot, **options)

    return make


@pytest.fixture
def dxl_robot(felis_stack):
    """Factory: ``dxl_robot(vb, robot=None, *, baud=None, connect=True, **options)`` → a connected
    `DynamixelRobot` on the virtual bus ``vb`` (or on a port path, with ``robot``). Closed (torque off, read
    back) at the end of the test, before its bus stops."""
    from felis.testing.resources import open_dxl_robot

    def make(on, robot=None, **options):
        return open_dxl_robot(felis_stack, on, robot, **options)

    return make


@pytest.fixture
def run(tmp_path):
    """``run(robot, controller, seconds, *, log=True, rate=None, clock=None, …)`` → `RunResult` (``.report``,
    ``.log``: the MCAP log read back, ``.path``). ``controller``: a controller object or a name (``"stand"``,
    ``"hold"``, …); ``log``: True (a new file in ``tmp_path``), False, or a path."""
    from felis.testing.runner import run_controller

    made = []

    def go(robot, controller, seconds, *, log=True, **options):
        path = None
        if log is True:
            made.append(None)
            path = tmp_path / f"run-{len(made)}.mcap"
        elif log:
            path = Path(log)
        return run_controller(robot, controller, seconds, log=path, **options)

    return go
