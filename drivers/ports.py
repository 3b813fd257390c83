"""The one port opener: which serial device a command talks to, and what has to run behind it.

A command names its servo bus as a device path (``/dev/ttyUSB0``), as ``virtual`` (a virtual bus of the
robot's emulated servos, started here in a child process through `felis.drivers.virtual.spawn`), or not
at all (then ``$FELIS_PORT``). `open_ports` resolves that, starts the virtual bus if asked, opens the
Dynamixel bus if asked, and hands back one `Ports`: the bus, the device path, the IMU's port (the one
given, else the virtual bus's simulated IMU) and the child process; leaving the ``with`` block closes
the bus and stops the child, whichever way it is left.

A virtual bus backed by MuJoCo (``sim=True``) runs MuJoCo in the child process (``felis virtual-bus
--sim``), so nothing here imports the simulation.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.port import MARGIN_MS_VIRTUAL
from felis.drivers.dynamixel.trace import PacketTrace, TracedBus
from felis.drivers.virtual import spawn
from felis.errors import ParameterError

if TYPE_CHECKING:
    from felis.drivers.virtual import VirtualBusProcess

VIRTUAL = "virtual"  # the port name that starts a virtual bus
ENV = "FELIS_PORT"  # the port when none is given
NO_PORT = "no port: give --port PATH (see `felis find-port`) or --port virtual, or set FELIS_PORT"


def is_virtual(port: str | None) -> bool:
    """Whether ``port`` names a virtual bus rather than a device."""
    return port == VIRTUAL


def resolve(port: str | None) -> str:
    """``port``, else ``$FELIS_PORT``; ParameterError (one line saying what to give) when neither is set."""
    port = port or os.environ.get(ENV)
    if not port:
        raise ParameterError(NO_PORT)
    return port


@dataclass
class Ports:
    """What `open_ports` opened. ``port`` is the device to open (the virtual bus's pseudo-terminal for
    ``virtual``); ``bus`` is None unless asked for; ``child`` is the virtual bus process, if any."""

    name: str  # the port as the command named it: a path or "virtual"
    port: str
    imu_port: str | None = None
    bus: DynamixelBus | None = None
    child: VirtualBusProcess | None = None

    @property
    def virtual(self) -> bool:
        return self.child is not None


@contextlib.contextmanager
def open_ports(port: str | None, *, robot: str = "cat", baud: int = 1_000_000, imu_port: str | None = None,
               bus: bool = True, retries: int = 1, quiet_check: bool = True, sim: bool = False,
               servo_params: str | os.PathLike | None = None, fixed_base: bool = False,
               drop: Sequence[float] | None = None, trace: PacketTrace | None = None) -> Iterator[Ports]:
    """Open the servo bus named ``port`` (a path, ``virtual``, or None for ``$FELIS_PORT``).

    ``virtual`` spawns a virtual bus for ``robot`` at ``baud``; ``sim``, ``servo_params``, ``fixed_base``
    and ``drop`` go to `spawn` (its simulation). ``bus``: also open a `DynamixelBus` (with ``retries``; on a
    virtual bus 40 ms of reply slack, `MARGIN_MS_VIRTUAL`, unless ``$FELIS_TIMEOUT_MARGIN_MS`` says otherwise)
    and, with ``quiet_check``, listen 50 ms first and refuse a port that talks unprompted (the IMU's,
    given as the bus: `DynamixelBus.check_quiet`; the emergency stop skips it, it never waits before it
    sends). ``imu_port``: the IMU's serial device; without one, a virtual bus's simulated IMU. ``trace``: write
    every packet of the bus to this `felis.drivers.dynamixel.trace.PacketTrace` (the caller closes it).
    """
    name = resolve(port)
    with contextlib.ExitStack() as stack:
        out = Ports(name=name, port=name, imu_port=imu_port)
        if is_virtual(name):
            child = stack.enter_context(spawn(robot, sim=sim, baud=baud, servo_params=servo_params,
                                              fixed_base=fixed_base, drop=drop))
            out.child, out.port, out.imu_port = child, child.port, imu_port or child.imu_port
        if bus:
            margin = (MARGIN_MS_VIRTUAL if out.virtual and not os.environ.get("FELIS_TIMEOUT_MARGIN_MS")
                      else None)  # None: the port's own default, or the variable's
            kw = dict(retries=retries, timeout_margin_ms=margin)
            out.bus = stack.enter_context(DynamixelBus(out.port, baud, **kw) if trace is None
                                          else TracedBus(out.port, baud, trace=trace, **kw))
            if quiet_check:
                out.bus.check_quiet()
        yield out
