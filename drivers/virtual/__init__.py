"""The virtual Dynamixel bus: X-series servos emulated byte for byte (Protocol 2.0) on a pseudo-terminal.

Any serial client, the unmodified ``dynamixel-sdk`` included, opens ``bus.port`` (a ``/dev/pts/N``
device) and talks to the servos exactly as through a USB adapter (``shared/reference/dynamixel.md``).

    memory.py     the control-table addresses the emulator acts on, write plans, hardware error bits
    packets.py    status packets (cached CRC prefix), the fast-read packet, instruction groups
    servo.py      VirtualServo: control-table memory, hardware errors (the servo model: instructions.py, horn.py)
    instructions.py  the instruction rules: who answers, READ/WRITE checks, REBOOT, FACTORY_RESET, …
    horn.py       the horn: position frame, standalone dynamics, Bus Watchdog; Mount
    dispatch.py   one instruction packet -> the replies of the servos on the wire (collisions, group reads)
    faultplan.py  FaultPlan, parse_fault_plan: the faults a bus injects, and their spec text
    server.py     VirtualBus: the pty server (wire time, faults, counters), for_robot; client_baud
    backend.py    HornBackend: the seam through which a simulation drives the horns (felis.sim.servo_in_loop)
    imu.py        VirtualImu: the emulated BNO08x of a backed robot, on a second pty
    process.py    spawn / VirtualBusProcess: the bus in a child process; main / serve: the child
    __main__.py   ``python -m felis.drivers.virtual OPTIONS_JSON``: the child's entry
"""

from felis.drivers.virtual.backend import BackendFactory, HornBackend
from felis.drivers.virtual.dispatch import dispatch
from felis.drivers.virtual.faultplan import FaultPlan, parse_fault_plan
from felis.drivers.virtual.imu import VirtualImu, check_imu_mount
from felis.drivers.virtual.memory import hardware_bits
from felis.drivers.virtual.packets import fast_packet, status_packet
from felis.drivers.virtual.process import VirtualBusProcess, spawn
from felis.drivers.virtual.server import BusStats, VirtualBus, client_baud
from felis.drivers.virtual.servo import Mount, VirtualServo

__all__ = [
    "BackendFactory", "BusStats", "FaultPlan", "HornBackend", "Mount", "VirtualBus", "VirtualBusProcess", "VirtualImu",
    "VirtualServo", "check_imu_mount", "client_baud", "dispatch", "fast_packet", "hardware_bits", "parse_fault_plan",
    "spawn", "status_packet",
]
