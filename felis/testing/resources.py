"""Robots and virtual buses for a test, each closed by the `contextlib.ExitStack` it is opened on.

The plugin's factory fixtures (`felis.testing.plugin`: ``sim_robot``, ``virtual_bus``, ``dxl_robot``) are these
functions bound to one stack per test; the stack closes everything in the reverse order it was opened, on every
way out of the test (pass, failure, error, Ctrl-C): a servo robot opened on a bus is closed (torque off and read
back) before the bus stops, a bus in a child process is stopped (SIGTERM, then SIGKILL), its pty closed.
Outside pytest they work the same on a stack of one's own::

    with contextlib.ExitStack() as stack:
        vb = open_virtual_bus(stack, "arm", sim=True)
        robot = open_dxl_robot(stack, vb)

MuJoCo, the drivers and the SDK are imported inside the functions, not with this module, so a pytest run that
never asks for a robot never loads them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from felis.errors import ParameterError
from felis.spec import RobotSpec, load_spec

if TYPE_CHECKING:
    from felis.drivers.dynamixel.robot import DynamixelRobot
    from felis.drivers.virtual import FaultPlan, VirtualBus, VirtualBusProcess
    from felis.sim import MujocoRobot

DEFAULT_BAUD = 1_000_000
SIM_OPTIONS = ("servo_params", "fixed_base", "imu_mount", "imu_drift", "drop")  # the simulation's (`spawn`'s too)


@dataclass(frozen=True)
class VirtualPort:
    """A running virtual bus as a test sees it: the device ``port`` a client opens (``str(vb)`` is it too),
    the robot's description, the baud rate, the simulated IMU's port (a cat backed by the simulation) and
    the bus itself: ``bus`` (in this process: change ``bus.faults``, ``bus.remove_servo(3)``,
    ``bus.servo(1).get("torque_enable")`` while a run goes on) or ``process`` (a child process)."""

    port: str
    spec: RobotSpec
    baud: int = DEFAULT_BAUD
    imu_port: str | None = None
    bus: VirtualBus | None = None
    process: VirtualBusProcess | None = None

    def __str__(self) -> str:
        return self.port

    def __fspath__(self) -> str:
        return self.port


def _spec(robot: str | RobotSpec) -> RobotSpec:
    return robot if isinstance(robot, RobotSpec) else load_spec(robot)


def open_sim_robot(stack: contextlib.ExitStack, robot: str | RobotSpec = "cat", *,
                   drop: float | Sequence[float] | None = None, **options) -> MujocoRobot:
    """A connected `felis.sim.MujocoRobot` (``robot``: cat, arm, a description file or a `RobotSpec`), closed
    by ``stack``. ``drop``: a height (m) or (height m, roll°, pitch°, yaw°): the robot placed at rest in the air
    (`felis.sim.scenarios.drop`), to fall when the run starts. ``options`` go to `MujocoRobot` (``servo``,
    ``fixed_base``, ``quantize``, ``edit``, …)."""
    from felis.sim import MujocoRobot
    from felis.sim.scenarios import drop as place

    sim = stack.enter_context(MujocoRobot(_spec(robot), **options))
    if drop is not None:
        place(sim, *((drop,) if isinstance(drop, int | float) else tuple(drop)))
    return sim


def open_virtual_bus(stack: contextlib.ExitStack, robot: str | RobotSpec = "cat", *,
                     faults: str | FaultPlan | None = None, sim: bool = False, process: bool = False,
                     baud: int = DEFAULT_BAUD, seed: int = 0, wire_time: bool = False, **options) -> VirtualPort:
    """A started virtual bus of ``robot``'s servos (`felis.drivers.virtual`), stopped by ``stack``.

    ``faults``: a fault spec (``"drop=0.01,hwerror=6:overload"``, `parse_fault_plan`) or a `FaultPlan`.
    ``sim=True`` backs the servos with the MuJoCo model (servo-in-the-loop, `felis.sim.servo_in_loop`; the cat's
    IMU on ``imu_port``). ``process=True`` serves the bus from a child process (`felis.drivers.virtual.spawn`):
    client and bus then do not share a GIL, as with real servos; ``robot`` must then be a name or a file, and
    ``faults`` spec text. ``options`` go to the builder: ``mount_offsets`` (joint → rad, in this process), and
    with ``sim``: ``servo_params`` (a `felis sysid` file), ``fixed_base``, ``imu_mount``, ``imu_drift``, ``drop``,
    and in this process ``lockstep`` (the simulation steps with the host's ticks: wrap the robot in
    `felis.sim.servo_in_loop.Lockstep`).
    """
    known = set(SIM_OPTIONS) | (set() if process else {"mount_offsets", "lockstep"})
    unknown = sorted(options.keys() - known)
    if unknown:
        raise ParameterError(f"virtual_bus{'(process=True)' if process else ''} does not take {', '.join(unknown)}; "
                             f"its options: faults, sim, process, baud, seed, wire_time, {', '.join(sorted(known))}")
    if process:
        if isinstance(robot, RobotSpec):
            raise ParameterError("virtual_bus(process=True) starts a child process: give the robot as a name or a "
                                 f"description file, not a RobotSpec ({robot.name})")
        if faults is not None and not isinstance(faults, str):
            raise ParameterError("virtual_bus(process=True): give the faults as spec text (e.g. 'drop=0.01'), "
                                 "a FaultPlan object cannot cross to a child process")
        from felis.drivers.virtual import spawn

        spec = load_spec(robot)
        child = stack.enter_context(spawn(robot, sim=sim, baud=baud, wire_time=wire_time, faults=faults or None,
                                          seed=seed, **options))
        return VirtualPort(child.port, spec, baud, imu_port=child.imu_port, process=child)
    spec = _spec(robot)
    if sim or options.keys() & {*SIM_OPTIONS, "lockstep"}:
        from felis.sim.servo_file import load_servo_params  # late: MuJoCo
        from felis.sim.servo_in_loop import virtual_bus

        if options.get("servo_params") is not None:
            options["servo_params"] = load_servo_params(options["servo_params"], spec)
        bus = virtual_bus(spec, sim=sim, baud=baud, faults=faults, seed=seed, wire_time=wire_time, **options)
    else:
        from felis.drivers.virtual import VirtualBus

        bus = VirtualBus.for_robot(spec, baud=baud, faults=faults, seed=seed, wire_time=wire_time, **options)
    stack.enter_context(bus)  # starts it; stops it (threads joined, ptys closed) when the stack closes
    return VirtualPort(bus.port, spec, baud, imu_port=bus.imu_port, bus=bus)


def open_dxl_robot(stack: contextlib.ExitStack, on: VirtualPort | str, robot: str | RobotSpec | None = None, *,
                   baud: int | None = None, connect: bool = True, timeout_margin_ms: float | None = None,
                   **options) -> DynamixelRobot:
    """A `felis.drivers.dynamixel.robot.DynamixelRobot` on ``on`` (a `VirtualPort`, whose robot, baud and IMU port
    it takes, or a device path with ``robot`` given), connected unless ``connect=False``; ``stack`` closes it
    (torque off, read back) before anything opened earlier, such as its bus. ``timeout_margin_ms``: slack on every
    reply timeout (`DynamixelBus`; default ``$FELIS_TIMEOUT_MARGIN_MS`` or 10 ms on a pty: raise it on a loaded
    machine, where a starved bus thread answers late). ``options`` go to `DynamixelRobot` (``calibration``,
    ``imu_port``, ``bus_watchdog_s``, ``hardware_poll_s``, ``retries``, …)."""
    from felis.drivers.dynamixel.bus import DynamixelBus
    from felis.drivers.dynamixel.robot import DynamixelRobot

    if isinstance(on, VirtualPort):
        spec = on.spec if robot is None else _spec(robot)
        port, baud = on.port, on.baud if baud is None else baud
        options.setdefault("imu_port", on.imu_port)
    elif isinstance(on, str):
        if robot is None:
            raise ParameterError(f"dxl_robot on {on}: say which robot is on that port (robot='cat' or 'arm')")
        spec, port, baud = _spec(robot), on, DEFAULT_BAUD if baud is None else baud
    else:
        raise ParameterError(f"dxl_robot needs a virtual bus (the virtual_bus fixture's) or a port path, got "
                             f"{type(on).__name__}")
    if timeout_margin_ms is not None:
        options["bus"] = DynamixelBus(port, baud, retries=options.pop("retries", 1),
                                      timeout_margin_ms=timeout_margin_ms,
                                      fast_sync_read=options.pop("fast_sync_read", True))
    hw = DynamixelRobot(spec, port, baud, **options)
    if connect:
        return stack.enter_context(hw)  # a failed connect releases the port at once (RobotBase.__enter__)
    stack.callback(hw.close)
    return hw
