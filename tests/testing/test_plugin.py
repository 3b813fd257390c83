"""felis.testing: the pytest plugin's fixtures, the run helper and the log assertions, on real parts.

The plugin is checked as pytest loads it (through the ``pytest11`` entry point, in pytest's own ``pytester``
runs): its fixtures exist without any import and vanish with ``-p no:felis``, loading it imports nothing heavy,
and a test that fails, errors in set-up, raises mid-run or gets a real SIGINT mid-run still leaves every robot
closed with torque off (read from the emulated servos), every bus stopped and every child process ended. Each
assertion is shown to pass on a log that meets it and to fail, naming joint, time and value, on one that does
not; the logs are real runs (MuJoCo, or the dynamixel-sdk on a virtual bus with injected faults).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.metadata
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.hal import Lifecycle
from felis.spec import load_spec
from felis.testing import (
    FAULT_EVENTS,
    VirtualPort,
    assert_event,
    assert_joint_within,
    assert_no_event,
    assert_no_fault,
    faults_in,
    open_sim_robot,
    run_controller,
)

pytest_plugins = ["pytester"]

RATE = 50.0  # servo runs: wall clock, a rate a loaded 2-core machine keeps


@pytest.fixture(autouse=True)
def _patient_bus(monkeypatch):
    """A loaded 2-core machine: room for a scheduling hiccup before a reply counts as lost (as tests/cli do, with
    more: a reply that comes after its timeout is taken as the answer to the next request of that servo, and a
    late PING reply once read as the arm gripper's Operating Mode 252 at connect — Model Number 1020's low byte)."""
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "100")


# ------------------------------------------------------------------------------------------- the plugin itself
def test_the_plugin_is_registered_through_the_pytest11_entry_point():
    eps = {e.name: e.value for e in importlib.metadata.entry_points(group="pytest11")}
    assert eps.get("felis") == "felis.testing.plugin"


def test_fixtures_come_from_the_entry_point_and_go_with_p_no_felis(pytester):
    pytester.makepyfile(test_uses="""
        def test_names(sim_robot, virtual_bus, dxl_robot, run, felis_stack):
            assert all(callable(f) for f in (sim_robot, virtual_bus, dxl_robot, run))
    """)
    pytester.inline_run().assertoutcome(passed=1)
    off = pytester.runpytest_inprocess("-p", "no:felis")
    off.assert_outcomes(errors=1)
    off.stdout.fnmatch_lines(["*fixture 'sim_robot' not found*"])


_PROBE = """
import json, sys
import felis.testing.plugin, felis.testing
heavy = ("mujoco", "torch", "dynamixel_sdk", "serial", "foxglove", "mcap", "matplotlib", "felis.sim", "felis.drivers",
         "felis.logs", "felis.controllers", "felis.learning", "felis.cli")
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in heavy or m.startswith(heavy))))
"""


def test_loading_the_plugin_imports_nothing_heavy():
    """Every pytest run in this environment loads the plugin: it must not pull in MuJoCo, the SDK or the log
    writer (they load inside the fixtures)."""
    res = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout) == []


class _Keep:
    """A plugin for the inner pytest run: its ``keep`` fixture hands what the inner test built to this test."""

    def __init__(self):
        self.items: dict[str, object] = {}

    @pytest.fixture
    def keep(self):
        return self.items


def test_a_failing_test_still_closes_everything(pytester):
    """The inner tests arm servos through the SDK, start buses in this process and in a child, then fail in three
    ways (an assertion, a set-up error, an exception inside a run); afterwards every robot is closed, every
    servo's torque is off (written through the port before the bus stopped), every bus stopped, the child ended,
    and the aborted run's log closed and readable."""
    pytester.makepyfile(test_inner="""
        import pytest

        class Boom:
            def reset(self, spec, state):
                self.n = 0
            def __call__(self, state):
                self.n += 1
                if self.n == 3:
                    raise RuntimeError("controller failed")
                from felis.hal import Command
                return Command(q=state.q)

        def test_fails(sim_robot, virtual_bus, dxl_robot, keep):
            keep["sim"] = sim = sim_robot("arm")
            sim.arm()
            keep["vb"] = vb = virtual_bus("cat")
            keep["hw"] = hw = dxl_robot(vb)
            hw.arm()
            keep["child"] = child = virtual_bus("arm", process=True)
            keep["hw2"] = dxl_robot(child)
            raise AssertionError("the inner test fails here on purpose")

        def test_set_up_fails(sim_robot, virtual_bus, keep):
            keep["sim_b"] = sim_robot("cat")
            virtual_bus("cat", faults="drop=2")  # not a fraction: ParameterError before anything starts

        def test_run_raises(virtual_bus, dxl_robot, run, keep, tmp_path):
            keep["vb_c"] = vb = virtual_bus("arm")
            keep["hw_c"] = hw = dxl_robot(vb)
            keep["log_c"] = tmp_path / "run-1.mcap"
            run(hw, Boom(), 1.0, rate=50)
    """)
    keep = _Keep()
    rec = pytester.inline_run(plugins=[keep])
    passed, skipped, failed = rec.listoutcomes()
    assert not passed and len(failed) == 3, [r.nodeid for r in passed]
    reports = {r.nodeid.split("::")[-1]: r for r in failed}
    assert "on purpose" in str(reports["test_fails"].longrepr)
    assert "must be a fraction" in str(reports["test_set_up_fails"].longrepr)
    assert "controller failed" in str(reports["test_run_raises"].longrepr)
    got = keep.items
    for name in ("sim", "hw", "hw2", "sim_b", "hw_c"):
        assert got[name].lifecycle is Lifecycle.DISCONNECTED, name
    for name in ("hw", "hw2", "hw_c"):
        assert not got[name].bus.is_open, f"{name} still holds its port"
    for name in ("vb", "vb_c"):
        bus = got[name].bus
        assert not bus.port_open, f"{name}: pty still open"
        torque = {s.id: s.get("torque_enable") for s in bus.servos}
        assert set(torque.values()) == {0}, f"{name}: torque left on: {torque}"
    assert got["vb"].bus._server is not None and not got["vb"].bus._server.is_alive()
    assert got["child"].process.proc.returncode is not None, "the child bus process outlived the test"
    from felis.logs.reader import read_log

    log = read_log(got["log_c"])
    assert log.complete and log.summary == {"error": "run aborted"}
    assert_event(log, "armed")


def test_ctrl_c_mid_run_still_closes_everything(pytester):
    """A real SIGINT in the middle of a run on servos ends the pytest session; the run stops as interrupted with
    torque off, its log is closed, and the session's teardown closes the robot and stops the bus."""
    pytester.makepyfile(test_inner="""
        import os, signal

        def test_interrupted(virtual_bus, dxl_robot, run, keep, tmp_path):
            keep["vb"] = vb = virtual_bus("arm")
            keep["hw"] = hw = dxl_robot(vb)
            ticks = []

            def ctrl_c(state, command):
                ticks.append(state.t)
                if len(ticks) == 5:
                    os.kill(os.getpid(), signal.SIGINT)

            keep["res"] = run(hw, "hold", 2.0, rate=50, monitors=[ctrl_c])
            keep["after"] = [s.get("torque_enable") for s in vb.bus.servos]
            raise KeyboardInterrupt  # as pytest would on the next Ctrl-C
    """)
    keep = _Keep()
    rec = pytester.inline_run(plugins=[keep], no_reraise_ctrlc=True)
    assert rec.ret == pytest.ExitCode.INTERRUPTED
    res = keep.items["res"]
    assert res.report.stopped == "interrupted (SIGINT)" and res.report.ticks == 4  # the 5th cut short
    assert_event(res, "interrupted", signal="SIGINT")
    assert res.log.complete and keep.items["after"] == [0] * 5
    assert keep.items["hw"].lifecycle is Lifecycle.DISCONNECTED and not keep.items["vb"].bus.port_open


# ------------------------------------------------------------------------------------------- factories and run
def test_sim_robot_drop_and_run_with_its_log(sim_robot, run, tmp_path):
    cat = sim_robot("cat", drop=0.3)
    assert cat.lifecycle is Lifecycle.CONNECTED and cat.read().height > 0.3
    res = run(cat, "hold", 0.6)
    assert res.ok and res.report.clock == "sim" and res.path.parent == tmp_path
    assert len(res.log.t) == res.report.ticks == 60 and res.log.joints == list(cat.spec.names)
    assert res.log.height[0] - res.log.height[-1] > 0.2, "the cat should have fallen"
    again = run(cat, "hold", 0.1)
    assert again.path != res.path and again.ok
    assert run(cat, "hold", 0.1, log=False).log is None


def test_run_builds_a_controller_by_name_and_refuses_options_with_an_object(sim_robot, run):
    from felis.controllers import PoseController

    arm = sim_robot("arm")
    with pytest.raises(ParameterError, match=r"go with a controller name"):
        run(arm, PoseController("stand"), 0.1, pose="sit")
    with pytest.raises(ParameterError, match=r"unknown controller 'crawl'"):
        run(arm, "crawl", 0.1)
    res = run(arm, "zero", 0.2)
    assert res.log.meta["controller"] == "zero" and res.log.meta["backend"] == "sim"
    # the balance monitor needs the cat's body model: run() loads it from the MJCF, as `felis run` does
    res = run(sim_robot("cat"), "balance", 0.2, reaction="brace")
    assert res.ok and res.log.meta["controller"] == "stand+balance"


def test_virtual_bus_and_dxl_robot_refuse_what_they_cannot_do(virtual_bus, dxl_robot):
    from felis.drivers.virtual import FaultPlan

    vb = virtual_bus("cat", faults="drop=0.01,remove=4")
    assert isinstance(vb, VirtualPort) and str(vb) == vb.port and vb.bus.faults.drop == 0.01
    assert vb.bus.faults.remove == (4,)
    with pytest.raises(ParameterError, match=r"FaultPlan object cannot cross"):
        virtual_bus("cat", process=True, faults=FaultPlan(drop=0.1))
    with pytest.raises(ParameterError, match=r"not a RobotSpec \(arm\)"):
        virtual_bus(load_spec("arm"), process=True)
    with pytest.raises(ParameterError, match=r"virtual_bus does not take speed; its options: faults, sim, .*mount_off"):
        virtual_bus("cat", speed=3)
    with pytest.raises(ParameterError, match=r"virtual_bus\(process=True\) does not take mount_offsets"):
        virtual_bus("cat", process=True, mount_offsets={"tail_yaw": 0.1})
    with pytest.raises(ParameterError, match=r"needs sim=True"):
        virtual_bus("cat", drop=(0.3, 0, 0, 0))
    with pytest.raises(ParameterError, match=r"say which robot"):
        dxl_robot(vb.port)
    with pytest.raises(ParameterError, match=r"needs a virtual bus"):
        dxl_robot(42)
    arm_bus = virtual_bus(load_spec("arm"))
    hw = dxl_robot(arm_bus.port, "arm")
    assert hw.lifecycle is Lifecycle.CONNECTED and hw.spec.name == "arm"


def test_a_servo_parameter_file_reaches_the_simulated_servos(virtual_bus, tmp_path):
    from felis.calib import sysid
    from felis.sim.servo_file import save_servo_params

    arm = load_spec("arm")
    no_i = {"joint2": sysid.with_gains(arm.joints[1], sysid.default_params(arm)["joint2"], (600, 0, 50))}
    path = save_servo_params(tmp_path / "arm.json", "arm", no_i)
    fitted = virtual_bus("arm", sim=True, servo_params=path).bus.backend.robot
    datasheet = virtual_bus("arm", sim=True).bus.backend.robot
    assert datasheet._ctl[1].kd == 0 and fitted._ctl[1].kd > 0  # the file's D = 50 reached joint2
    assert fitted._ctl[2] == datasheet._ctl[2]  # and nothing else


def test_servo_in_the_loop_arm_reaches_its_pose_through_the_sdk(virtual_bus, dxl_robot, run):
    vb = virtual_bus("arm", sim=True)
    res = run(dxl_robot(vb), "stand", 1.2, rate=RATE)
    assert res.report.clock == "wall" and res.log.meta["backend"] == "dxl"
    stand = load_spec("arm").pose("stand")
    for name, q in zip(res.log.joints, stand, strict=True):
        assert_joint_within(res, name, q - 0.1, q + 0.1, t=(1.0, None))
    assert_no_fault(res, comm_errors=None)  # a loaded machine may lose a reply on the wall clock
    assert_event(res, "stopped", reason="duration")


def test_open_sim_robot_outside_pytest_closes_with_its_stack():
    with contextlib.ExitStack() as stack:
        arm = open_sim_robot(stack, "arm")
        res = run_controller(arm, "hold", 0.1)
        assert res.log is None and res.ok
    assert arm.lifecycle is Lifecycle.DISCONNECTED


# ------------------------------------------------------------------------------------------- assertions
@pytest.fixture(scope="module")
def sit(tmp_path_factory):
    """A MuJoCo cat moving from its start pose to ``sit`` over 1.5 s, held to 2 s (deterministic)."""
    with contextlib.ExitStack() as stack:
        cat = open_sim_robot(stack, "cat")
        return run_controller(cat, "sit", 2.0, log=tmp_path_factory.mktemp("sit") / "sit.mcap")


def test_joint_within_passes_inside_and_names_joint_time_and_value_outside(sit):
    log = sit.log
    k = log.joints.index("fl_pitch")
    assert_joint_within(sit, "fl_pitch", log.q[:, k].min(), log.q[:, k].max())
    assert_joint_within(log, "fl_pitch", 0.25, 0.45, t=(1.8, None))  # the sit pose's 0.35 rad, reached
    late = log.t >= 1.8
    with pytest.raises(AssertionError) as e:
        assert_joint_within(log, "fl_pitch", -0.05, 0.05, t=(1.8, None))
    worst = log.q[late, k].max()
    msg = str(e.value)
    assert msg.startswith("fl_pitch left [-0.0500, 0.0500] in t ∈ [1.800, …] s")
    assert f"{late.sum()} of {late.sum()} state samples outside" in msg
    assert f"first at t={log.t[late][0]:.3f} s" in msg and f"({worst:.4f}, {worst - 0.05:.4f} above the band)" in msg
    assert_joint_within(log, "fl_pitch", -0.05, 0.05, t=(0.0, 0.0))  # the start pose
    with pytest.raises(AssertionError, match=r"fl_pitch left .* command samples outside"):
        assert_joint_within(log, "fl_pitch", -0.05, 0.05, t=(1.8, None), commanded=True)


def test_joint_within_counts_a_missing_value_and_an_empty_window_as_failures(sit):
    q = sit.log.q.copy()
    q[50, sit.log.joints.index("tail_yaw")] = np.nan
    holed = dataclasses.replace(sit.log, q=q)
    with pytest.raises(AssertionError, match=rf"1 of {len(q)} state samples outside; first at t=0\.500 s \(missing\)"):
        assert_joint_within(holed, "tail_yaw", -1, 1)
    with pytest.raises(AssertionError, match=r"no state samples of tail_yaw in t ∈ \[5\.000, 6\.000\] s "
                                             r"\(the log has 0\.000…1\.990 s\)"):
        assert_joint_within(sit, "tail_yaw", -1, 1, t=(5, 6))


@pytest.mark.parametrize(("call", "match"), [
    (lambda log: assert_joint_within(log, "tail", 0, 1), r"no joint 'tail' in the log of cat; its joints: spine_pitch"),
    (lambda log: assert_joint_within(log, "tail_yaw", 1, 0), r"band \[1.0, 0.0\] for tail_yaw is empty"),
    (lambda log: assert_event(log, "armed", t=(2, 1)), r"must have t0 ≤ t1"),
    (lambda log: assert_event(log, "armed", t=3), r"t must be a window"),
    (lambda log: assert_no_event(log, "armed", t=("start", 1)), r"t must be a window \(t0, t1\) in seconds"),
    (lambda log: assert_no_fault(str(log.path)), r"expected a run log"),
])
def test_misuse_is_a_parameter_error_not_a_failed_check(sit, call, match):
    with pytest.raises(ParameterError, match=match):
        call(sit.log)


def test_a_run_without_a_log_cannot_be_asserted_on(sim_robot, run):
    res = run(sim_robot("arm"), "hold", 0.05, log=False)
    with pytest.raises(ParameterError, match=r"kept no log: run it with log=True"):
        assert_no_fault(res)


def test_event_found_with_its_details_and_missing_ones_listed(sit):
    (armed,) = assert_event(sit, "armed", t=(0, 0.01))
    assert armed["t"] == 0.0
    (stop,) = assert_event(sit, "stopped", reason="duration", count=1)
    assert stop["detail"]["ticks"] == sit.report.ticks
    with pytest.raises(AssertionError, match=r"expected a 'stopped' event with reason='watchdog' over the whole run "
                                             r"at least once; the 'stopped' events logged: stopped at t=1\.990 s "
                                             r"reason='duration', ticks=200"):
        assert_event(sit, "stopped", reason="watchdog")
    with pytest.raises(AssertionError, match=r"2 time\(s\), found 1"):
        assert_event(sit, "armed", count=2)
    with pytest.raises(AssertionError, match=r"expected a 'hardware_error' event .*; the log's events: armed at "
                                             r"t=0\.000 s; stopped at t=1\.990 s"):
        assert_event(sit, "hardware_error")
    with pytest.raises(AssertionError, match=r"'armed' event in t ∈ \[0\.500, …\] s"):
        assert_event(sit, "armed", t=(0.5, None))
    assert_no_event(sit, "hardware_error")
    assert_no_event(sit, "armed", t=(0.5, None))
    with pytest.raises(AssertionError, match=r"1 'armed' event\(s\) over the whole run: armed at t=0\.000 s"):
        assert_no_event(sit, "armed")


def test_no_fault_passes_a_clean_run_and_names_a_servo_switched_off(sit, virtual_bus, dxl_robot, run):
    assert faults_in(sit) == []
    assert_no_fault(sit)
    vb = virtual_bus("cat", faults="torque_off=7@0.2")
    res = run(dxl_robot(vb), "hold", 1.0, rate=RATE)
    assert not res.ok and res.report.stopped.startswith("torque lost")
    with pytest.raises(AssertionError) as e:
        assert_no_fault(res, comm_errors=None)
    msg = str(e.value)
    assert re.search(r"fault\(s\) in run-1\.mcap:\n  t=\d\.\d{3} s: torque_lost detail=.torque lost: fr_pitch "
                     r"\(ID 7\) switched off", msg), msg
    assert "the run stopped: torque lost: fr_pitch (ID 7)" in msg
    (lost,) = assert_event(res, "torque_lost", t=(0.2, None))
    assert_no_event(res, "torque_lost", t=(None, lost["t"] - 1e-6))


def test_no_fault_tolerates_lost_replies_only_up_to_what_it_is_told(virtual_bus, dxl_robot, run):
    vb = virtual_bus("cat", faults="drop=0.03", seed=3)
    res = run(dxl_robot(vb, timeout_margin_ms=40), "hold", 0.6, rate=RATE)  # each lost reply waits the margin
    assert res.ok, res.report.stopped
    failed = res.report.comm["failed_transactions"]
    assert failed > 0, f"3 % dropped replies over {res.report.ticks} ticks lost no transaction: {res.report.comm}"
    with pytest.raises(AssertionError, match=rf"{failed} failed bus transactions in all \(allowed 0: "):
        assert_no_fault(res)
    with pytest.raises(AssertionError, match=rf"allowed {failed - 1}"):
        assert_no_fault(res, comm_errors=failed - 1)
    assert_no_fault(res, comm_errors=failed)
    assert_no_fault(res, comm_errors=None)


def test_fault_events_cover_every_error_level_event_of_the_log():
    from foxglove.messages import LogLevel

    from felis.logs.runlog import _LEVEL

    errors = {k for k, level in _LEVEL.items() if level == LogLevel.Error}
    assert errors and errors <= set(FAULT_EVENTS)
