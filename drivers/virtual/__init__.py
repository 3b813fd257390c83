"""The virtual Dynamixel bus: X-series servos emulated byte for byte (Protocol 2.0) on a pseudo-terminal.

Any serial client, the unmodified ``dynamixel-sdk`` included, opens ``bus.port`` (a ``/dev/pts/N``
device) and talks to the servos exactly as through a USB adapter (``shared/reference/dynamixel.md``).

Pieces
------
* `VirtualServo`: one servo: its control-table memory (`felis.drivers.dynamixel.controltable`), the rules of
  every instruction, and either standalone dynamics or a horn driven by a simulation.
* `dispatch`: one instruction packet → the status packets the servos on the wire send back.
* `VirtualBus`: servos by ID on a pty, a server thread that parses what the client writes, dispatches
  it and writes the replies (immediately, or at the times the wire would deliver them), fault
  injection, counters; ``VirtualBus.for_robot`` builds the servos of a robot description, optionally
  backed by the MuJoCo model (servo-in-the-loop) and, for the cat, with its IMU on a second pty.
* `spawn` / `VirtualBusProcess`: the same bus in a child process (``felis virtual-bus``), so a client
  and the bus do not share a GIL (benchmarks, demos).

Servo model (choices the reference leaves open are marked ▸)
----------------------------------------------------------
Status Return Level (addr 68): 0 answers PING only, 1 also READ and the group reads, 2 everything.
A packet to the broadcast ID gets no status except PING (every servo answers, in ascending ID order)
and the group reads. ▸ The level, the ID and the Alert bit of a reply are those in force when the
instruction arrived: a write that changes the ID, the baud rate or the level is acknowledged with the
old ones (old ID, old baud), then takes effect.

Status errors (bits 0-6 of the error byte; bit 7 = Alert while Hardware Error Status ≠ 0). An
instruction that fails changes nothing (writes are atomic). ▸ A write is checked in this order: length
and extent (Data Length, then Data Range for the address range), access (read-only items, then the
EEPROM lock), every value against its item (Data Range), limits (Data Limit), then Result Fail.

* CRC Error: a well-framed packet for this ID whose CRC does not match.
* Instruction Error: an unknown instruction; ACTION with nothing registered (e-Manual); ▸ a group
  instruction (SYNC_/BULK_…) sent to a single ID instead of the broadcast ID.
* Data Length Error: wrong parameter count (PING ignores parameters; READ needs 4; WRITE/REG_WRITE
  at least 3; FACTORY_RESET 1); ▸ a READ or WRITE of length 0; a write that covers only part of an
  item (e.g. 2 bytes of Goal Position).
* Data Range Error: ▸ a read or write that runs past the end of the control table, or a write that
  covers no item at all (gaps between items are not memory: written gap bytes are ignored, read gap
  bytes are 0); a value outside the item's lo…hi or not one of its codes (baud rate, operating mode);
  FACTORY_RESET with an option other than 0xFF/0x01/0x02.
* Access Error: writing a read-only item; writing an EEPROM item (addr < 64) while Torque Enable is 1;
  FACTORY_RESET while Torque Enable is 1.
* Data Limit Error: Goal Position outside Min…Max Position Limit in position mode (3); ▸ also
  |Goal Velocity| above Velocity Limit and |Goal Current| above Current Limit.
* Result Fail: ▸ writing Torque Enable = 1 while a shutdown is latched (below).

Hardware errors: `VirtualServo.raise_hardware_error` sets bits of Hardware Error Status (addr 70).
A bit that is also set in Shutdown (addr 63, factory 52 = overheating | electrical shock | overload)
turns torque off and latches: Torque Enable = 1 is refused (Result Fail) until REBOOT. REBOOT sends
its status first, then clears addr 70 and the latch, turns torque off and puts the RAM area
(addr ≥ 64) back to its defaults; EEPROM is kept. FACTORY_RESET (refused while torque is on) puts
everything back to factory values except, for option 0x01, the ID and, for 0x02, the ID and the baud
rate; ▸ it also clears hardware errors (it reboots the servo). ▸ At boot (construction, REBOOT,
FACTORY_RESET) Goal Position is set to the Present Position, as X-series firmware does, so enabling
torque without writing a goal holds the horn where it is. CLEAR answers OK; ▸ with the multi-turn
magic (01 44 58 4C 22) in extended position mode it drops whole turns from the horn angle.
REG_WRITE validates and stores one write and sets Registered Instruction (addr 69); ACTION applies
it (and answers the write's error if, in between, it became invalid). ▸ Bus Watchdog, Profile
Acceleration, time-based profiles (Drive Mode bit 2), PWM and current control modes are not
modelled: in modes 0 and 16 the horn holds still.

Position frame: the horn angle θ (rad, 0 at the centre tick 2048, positive counter-clockwise) gives

    Present Position = 2048 + s·round(θ / (2π/4096)) + Homing Offset      s = −1 if Drive Mode bit 0 else +1

and Goal Position is read in the same frame. Present Velocity = s·ω in 0.229 rpm units; Present
Current = s·τ / kt in the model's current unit with kt = stall torque / stall current (XL330 1.47 A,
XM430 2.3 A); the XL430's address 126 is Present Load = s·τ / stall torque in 0.1 %. Moving = 1 while
|Present Velocity| > Moving Threshold. Present Input Voltage is the datasheet's nominal supply,
Present Temperature a constant 32 °C, Realtime Tick counts milliseconds mod 32768.

Standalone dynamics (no simulation), updated lazily from the wall clock whenever the servo is accessed:
with torque on in a position mode (3, 4, 5) the horn follows the goal θg with first-order dynamics
(τ = 50 ms) capped at v_max = no-load speed (or Profile Velocity when non-zero and lower)::

    dθ/dt = clip((θg − θ)/τ, −v_max, v_max)

integrated exactly over the elapsed time (a linear, rate-limited phase, then the exponential);
in velocity mode (1) ω follows Goal Velocity with the same τ. Torque (and so current) is the position
controller's stiffness times the error, kp = stall·(P/128)·(4096/2π)/885 N·m/rad (as `felis.sim.servo`),
clipped at the stall torque. Torque off: the horn stays where it is.

Servo-in-the-loop (``VirtualBus.for_robot(…, sim=True)``): the horn is the MuJoCo joint. A thread
steps `felis.sim.robot.MujocoRobot` so that simulated time follows the wall clock (whole model
timesteps, at most 20 per iteration; a longer lag is skipped, not caught up, and counted in
``stats.sim_lag_s``). The servos boot with Goal Position at the model's initial pose. Each iteration
copies Goal Position (through the mounting, below), the Torque Enable mask (always the full mask) and
Profile Velocity (``dq_max``, None when all are 0; a 0 among others is unlimited) into a
`felis.hal.Command` when any servo's memory changed, and copies the quantised q, dq and effort back
into every servo's present items. ``servo_params`` and ``fixed_base`` pass through to the model
(`felis.sim.robot.MujocoRobot`: per-joint servo parameters, the robot hung on a stand). Mounting, per joint::

    θ = direction·q / m_per_rad + zero + mount_offset          (JointSpec fields; offset default 0)

IMU (a robot whose description has one, e.g. the cat): a BNO08x in UART-RVC mode
(`felis.drivers.imu.RvcEmulator`, 100 Hz) on ``bus.imu_port`` reports the model's IMU site (orientation
q_wb, specific force accel_b). ▸ While the robot is held (before torque first comes on) it is still in
the operator's hands: the accelerometer reads the reaction to gravity, accel_b = R(q_wb)ᵀ·(−g), not the
free fall a forward pass of the start pose shows (the cat's feet start 1 mm above the floor). ▸ Once
released, each sample's accelerometer reads the mean specific force over the sample period, like the
sensor's own low-pass filter: accel_b = R(q_wb)ᵀ·((v(t) − v(t₀))/(t − t₀) − g), v the IMU site's world
velocity and t₀ the previous sample's simulated time. An instantaneous reading would alias: the samples
follow the wall clock, and a landing's impact, a few milliseconds long, falls between them. Each axis
saturates at ±8 g (``ACCEL_RANGE_G``, the BNO08x accelerometer's full scale), as the real sensor does.

Drop (``drop=(height m, roll°, pitch°, yaw°)``, ``felis virtual-bus --sim --drop H,R,P,Y``): before the
servos and the IMU first publish, `felis.sim.scenarios.drop` places the floating base at rest, turned by
roll, pitch, yaw, its lowest point ``height`` above the floor. The operator holds it there (the servos
read the held joints, the IMU the turned orientation and the reaction to gravity) until torque first
comes on: that is the release, and free fall starts with the physics. A drop needs the floating base
(not ``fixed_base``); `check_drop` validates it (also in the parent, `spawn`).
``imu_mount`` / ``imu_drift`` (`felis.drivers.imu.SensorMount`) simulate a mis-mounted sensor whose
orientation drifts: q_ws = q_wb ⊗ q_bs ⊗ exp(ω_d·t), accel_s = R(q_bs)ᵀ·accel_b, t on the sample clock.

Wire
----
The client's baud rate is read from the pty master (``TCGETS2``: the slave's c_ospeed, custom rates
included; else ``tcgetattr`` and the standard B-constants; ▸ a rate that cannot be read counts as
"unknown" and every servo answers). A servo only hears packets sent at its own baud rate, so a scan
across rates finds each servo at its own. A partial packet followed by a 50 ms gap is discarded,
as a servo's receiver does. ▸ Servos that share an ID (factory-new ones: ID 1) answer in the same
slot and collide: the line is a wired-AND of both with their start bits a byte apart, so the client
gets one garbled packet (`_collide`), as on a real bus. ▸ In a SYNC_READ / BULK_READ the listed
servos that are present answer in list order and a missing one is simply skipped (the SDK then times out on it); in a
FAST_SYNC_READ / FAST_BULK_READ the header announces every listed servo, the present ones append
their segments and a missing one leaves the packet short (the SDK reports COMM_RX_CORRUPT).
SYNC_WRITE / BULK_WRITE with a malformed parameter block are ignored as a whole.

Timing: ``wire_time=False`` writes all replies to a packet at once, as soon as it is parsed (Return
Delay Time not modelled). ``wire_time=True`` models a half-duplex wire at the client's baud, 10 bits
per byte: a request occupies the wire for len·10/baud from when it is read (or from when the wire is
free), each replying servo waits its Return Delay Time (addr 9, ×2 µs) after the previous byte, then
its reply occupies len·10/baud; each reply is written when its last byte would have arrived. Replies
due later go into a schedule that the server thread keeps while it goes on reading: it polls until
0.3 ms before the next one is due, then spins on ``time.perf_counter`` and writes it. ▸ A fast-read
packet waits for the first servo's Return Delay Time only.

Faults (`Faults`, `parse_faults`): drop a fraction of replies, corrupt a fraction (one random byte
XOR-ed with a random non-zero mask), delay the replies to each request by N ms, remove servos
(silent: they neither answer nor act), raise hardware errors, close the port (to a client the device
vanishes, as an unplugged adapter) now or after N s. ▸ Delayed replies are scheduled, not slept on:
the bus keeps serving meanwhile, so a reply can arrive after the client gave up on it (its next
transaction then flushes or skips the stale packet), as with a slow adapter. ▸ A dropped reply still
occupies the wire in wire-time mode. All draws come from one seeded RNG, so a run is reproducible for
a given seed and packet sequence.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import heapq
import itertools
import math
import os
import random
import select
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import (
    BAUD_RATES,
    EEPROM_END,
    FAST_SYNC_READ_MIN_FIRMWARE,
    HARDWARE_ERRORS,
    Item,
    control_table,
)
from felis.errors import CommError, ParameterError
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, SERVOS, TICKS_PER_REV
from felis.spec import RobotSpec, load_spec

if TYPE_CHECKING:
    from felis.drivers.imu import SensorMount

TAU_S = 0.05  # first-order time constant of the standalone horn
GAP_S = 0.05  # inter-byte gap after which a partial packet is dropped
TEMPERATURE_C = 32
STALL_CURRENT_A = {"XL330-M288-T": 1.47, "XM430-W350-T": 2.3}
CENTRE = 2048
SPIN_S = 0.0003  # wire-time: sleep until this long before a reply is due, then spin
HOUSEKEEPING_S = 0.001  # the server thread checks the servos' own clocks (Bus Watchdog, timed faults) this often

# control-table addresses the emulator acts on
ID, BAUD, RETURN_DELAY, DRIVE_MODE, OPERATING_MODE, HOMING_OFFSET, MOVING_THRESHOLD = 7, 8, 9, 10, 11, 20, 24
CURRENT_LIMIT, VELOCITY_LIMIT, MAX_POSITION, MIN_POSITION, SHUTDOWN = 38, 44, 48, 52, 63
TORQUE_ENABLE, STATUS_RETURN_LEVEL, REGISTERED, HARDWARE_ERROR, POSITION_P = 64, 68, 69, 70, 84
BUS_WATCHDOG, GOAL_PWM, GOAL_CURRENT, GOAL_VELOCITY, PROFILE_VELOCITY, GOAL_POSITION = 98, 100, 102, 104, 112, 116
GOALS = frozenset((GOAL_PWM, GOAL_CURRENT, GOAL_VELOCITY, GOAL_POSITION))  # refused while the Bus Watchdog is tripped
WATCHDOG_UNIT_S = 0.02
WATCHDOG_ERROR = 0xFF  # Bus Watchdog reads -1 once tripped
REALTIME_TICK, MOVING, PRESENT_CURRENT, PRESENT_POSITION, PRESENT_VOLTAGE, PRESENT_TEMPERATURE = \
    120, 122, 126, 132, 144, 146
DYNAMIC_START = 120  # items from here on are refreshed from the dynamics before a read
POSITION_MODES = (3, 4, 5)
_CACHED = frozenset((DRIVE_MODE, HOMING_OFFSET, MOVING_THRESHOLD, POSITION_P))  # see VirtualServo._cache_settings
CLEAR_MULTI_TURN = b"\x01\x44\x58\x4c\x22"

_PRESENT = struct.Struct("<hii")  # present current/load, velocity, position at 126
_I32 = struct.Struct("<i")
_U16 = struct.Struct("<H")
_TCGETS2 = 0x802C542A  # _IOR('T', 0x2A, struct termios2), Linux
_TERMIOS2 = struct.Struct("<IIIIB19sII")
_BOTHER = 0o010000
_B_RATES = {getattr(termios, f"B{r}"): r for r in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000,
                                                   576000, 921600, 1000000, 1152000, 2000000, 2500000, 3000000,
                                                   3500000, 4000000) if hasattr(termios, f"B{r}")}

GROUP_READS = (P.SYNC_READ, P.FAST_SYNC_READ, P.BULK_READ, P.FAST_BULK_READ)
GROUP_WRITES = (P.SYNC_WRITE, P.BULK_WRITE)
READS = (P.READ, *GROUP_READS)  # answered at Status Return Level >= 1


# ----------------------------------------------------------------------------------------- mounting
@dataclass(frozen=True)
class Mount:
    """How a servo horn drives its joint: θ = direction·q/m_per_rad + zero + offset (rad; see module doc)."""

    direction: int = 1
    zero: float = 0.0
    m_per_rad: float = 1.0
    offset: float = 0.0

    def horn(self, q: float) -> float:
        """Joint position (rad or m) → horn angle θ (rad around tick 2048)."""
        return self.direction * q / self.m_per_rad + self.zero + self.offset

    def joint(self, theta: float) -> float:
        """Horn angle θ → joint position."""
        return self.direction * (theta - self.zero - self.offset) * self.m_per_rad


# ----------------------------------------------------------------------------------------- status packets
_PREFIX_CRC: dict[tuple[int, int, int], int] = {}


def status_packet(dxl_id: int, error: int, data: bytes = b"") -> bytes:
    """`protocol.status` with the CRC of the constant prefix cached (the hot path of every read)."""
    if b"\xff\xff\xfd" in data:
        return P.status(dxl_id, error, data)
    n = len(data) + 4
    key = (dxl_id, n, error)
    head = P.HEADER + bytes((dxl_id, n & 0xFF, n >> 8, P.STATUS, error))
    crc = _PREFIX_CRC.get(key)
    if crc is None:
        crc = _PREFIX_CRC[key] = P.crc16(head)
    crc = P.crc16(data, crc)
    return head + data + bytes((crc & 0xFF, crc >> 8))


def fast_packet(n_announced: int, segments: list[tuple[int, int, bytes]]) -> bytes:
    """A FAST_SYNC/BULK_READ status (ID 0xFE, not stuffed) announcing ``n_announced`` parameter bytes.

    Each servo appends ``ERR ID data CRC`` where its CRC covers every byte on the wire before it,
    earlier servos' CRC bytes included, so the last CRC is the whole packet's CRC (what the SDK
    checks). A missing servo's segment is absent and the packet is short of its announced length.
    """
    length = 1 + n_announced
    pkt = bytearray(P.HEADER + bytes((P.BROADCAST_ID, length & 0xFF, length >> 8, P.STATUS)))
    crc = P.crc16(pkt)
    for dxl_id, err, data in segments:
        seg = bytes((err & 0xFF, dxl_id)) + data
        crc = P.crc16(seg, crc)
        tail = bytes((crc & 0xFF, crc >> 8))
        pkt += seg + tail
        crc = P.crc16(tail, crc)
    return bytes(pkt)


# ----------------------------------------------------------------------------------------- write plans
@dataclass(frozen=True)
class _WritePlan:
    """What a write of ``length`` bytes at ``addr`` touches, checked once per (model, addr, length)."""

    error: int  # structural error (length / range / access), 0 if none
    items: tuple[tuple[Item, int], ...] = ()  # (item, offset in the data)
    eeprom: bool = False
    addrs: frozenset[int] = frozenset()


_PLANS: dict[tuple[str, int, int], _WritePlan] = {}


def _write_plan(table, addr: int, length: int) -> _WritePlan:
    key = (table.model, addr, length)
    plan = _PLANS.get(key)
    if plan is None:
        plan = _PLANS[key] = _make_plan(table, addr, length)
    return plan


def _make_plan(table, addr: int, length: int) -> _WritePlan:
    if length <= 0:
        return _WritePlan(P.DATA_LENGTH_ERROR)
    if addr + length > table.size:
        return _WritePlan(P.DATA_RANGE_ERROR)
    covered = sorted(table.covering(addr, length), key=lambda it: it.addr)
    if not covered:
        return _WritePlan(P.DATA_RANGE_ERROR)
    if any(it.addr < addr or it.addr + it.size > addr + length for it in covered):
        return _WritePlan(P.DATA_LENGTH_ERROR)
    if any(not it.writable for it in covered):
        return _WritePlan(P.ACCESS_ERROR)
    return _WritePlan(0, tuple((it, it.addr - addr) for it in covered), any(it.addr < EEPROM_END for it in covered),
                      frozenset(it.addr for it in covered))


def hardware_bits(bits_or_names: int | str | Iterable[str | int]) -> int:
    """Hardware Error Status bits from an int, a name (``"overload"``), ``"0x20"`` or a list of those."""
    if isinstance(bits_or_names, int) and not isinstance(bits_or_names, bool):
        if not 0 <= bits_or_names <= 0xFF:
            raise ParameterError(f"hardware error bits {bits_or_names} outside 0…255")
        return bits_or_names
    if isinstance(bits_or_names, str):
        bits_or_names = [p for p in bits_or_names.replace("+", ",").split(",") if p.strip()]
    by_name = {name: 1 << bit for bit, name in HARDWARE_ERRORS.items()}
    out = 0
    for part in bits_or_names:
        if isinstance(part, int):
            out |= hardware_bits(part)
            continue
        name = part.strip().lower().replace("-", "_").replace(" ", "_")
        if name in by_name:
            out |= by_name[name]
            continue
        try:
            out |= hardware_bits(int(name, 0))
        except ValueError:
            raise ParameterError(f"unknown hardware error {part!r}; known: {', '.join(by_name)} "
                                 "or a bit mask") from None
    return out


# ----------------------------------------------------------------------------------------- the servo
class VirtualServo:
    """One emulated X-series servo: control-table memory, instruction rules and dynamics (module doc).

    Args:
        model: model name (``"XL330-M288-T"``) or Model Number.
        id: servo ID (0…252).
        baud_bps: the baud rate it listens at (one of the model's Baud Rate codes).
        firmware: Firmware Version (default: the control table's).
        mount: how the horn drives a joint (only used to express the horn angle as a joint position).
        clock: time source for the standalone dynamics (seconds; default ``time.perf_counter``).

    ``handle(packet)`` runs one instruction packet against this servo alone and returns the status
    packets it sends; `VirtualBus` does the same for many servos on a pty.
    """

    def __init__(self, model: str | int, id: int = 1, baud_bps: int = 57600, *, firmware: int | None = None,
                 mount: Mount | None = None, clock: Callable[[], float] = time.perf_counter):
        self.table = control_table(model)
        self.model = self.table.model
        self.datasheet = SERVOS[self.model]
        if not 0 <= id <= P.MAX_ID:
            raise ParameterError(f"servo ID {id} outside 0…{P.MAX_ID}")
        baud_code = self._baud_code_for(baud_bps)
        self.firmware = self.table.item("firmware_version").default if firmware is None else int(firmware)
        if not 0 <= self.firmware <= 255:
            raise ParameterError(f"firmware version {firmware} outside 0…255")
        self.mount = mount or Mount()
        self.clock = clock
        self.external = False  # True: the horn is driven from outside (simulation); no own dynamics
        self.revision = 0  # +1 whenever memory changes through an instruction (the sim thread watches it)
        self.indirect = self.table.indirect  # (Indirect Address 1, Indirect Data 1, count) or None
        self._targets: list[int] = []  # per Indirect Data byte: the address it stands for
        self._last_rx = clock()  # when this servo last heard an instruction packet (Bus Watchdog)
        self.torque_on_at: float | None = None  # when torque first came on (timed faults count from it)
        self._registered: tuple[int, bytes] | None = None
        self._latched = False
        self._theta = 0.0  # horn angle (rad)
        self._omega = 0.0  # horn speed (rad/s)
        self._torque = 0.0  # horn torque (N·m)
        self._t = clock()
        self._t0 = self._t
        self._kt = (self.datasheet.stall_torque / STALL_CURRENT_A[self.model]
                    if self.model in STALL_CURRENT_A else None)
        unit = self.table.items.get("present_current")
        self._current_unit = unit.scale if unit is not None else None
        self.mem = bytearray()
        self._boot(self.table.defaults(), id, baud_code)

    # -------------------------------------------------------------- memory
    def _baud_code_for(self, baud_bps: int) -> int:
        for code, bps in self.table.baud_rates.items():
            if bps == baud_bps:
                return code
        raise ParameterError(f"{self.table.model} has no baud rate {baud_bps}; "
                             f"supported: {', '.join(str(b) for b in self.table.baud_rates.values())}")

    def _boot(self, mem: bytearray, dxl_id: int, baud_code: int) -> None:
        """Power-up: memory image, ID, baud, firmware, sensors, goal = present."""
        mem[ID] = dxl_id
        mem[BAUD] = baud_code
        mem[6] = self.firmware
        mem[PRESENT_TEMPERATURE] = TEMPERATURE_C
        _U16.pack_into(mem, PRESENT_VOLTAGE, round(self.datasheet.voltage * 10))
        self.mem = mem
        self.id = dxl_id
        self.baud_bps = BAUD_RATES[baud_code]
        self._registered = None
        self._latched = False
        self._omega = self._torque = 0.0
        self._cache_settings()
        self._map_indirect()
        self._last_rx = self.clock()
        self._refresh()
        _I32.pack_into(mem, GOAL_POSITION, _I32.unpack_from(mem, PRESENT_POSITION)[0])
        self.revision += 1

    def _cache_settings(self) -> None:
        """Items the dynamics read on every access, decoded once per change (the hot path)."""
        mem = self.mem
        self._s = -1 if mem[DRIVE_MODE] & 1 else 1
        self._homing = _I32.unpack_from(mem, HOMING_OFFSET)[0]
        self._moving_threshold = _I32.unpack_from(mem, MOVING_THRESHOLD)[0]
        stall = self.datasheet.stall_torque
        self._kp = stall * (_U16.unpack_from(mem, POSITION_P)[0] / 128.0) * (TICKS_PER_REV / (2.0 * math.pi)) \
            / PWM_LIMIT

    def _map_indirect(self) -> None:
        """The address each Indirect Data byte stands for, from the Indirect Address items."""
        if self.indirect is not None:
            a0, d0, n = self.indirect
            self._targets = [_U16.unpack_from(self.mem, a0 + 2 * k)[0] for k in range(n)]
            # runs of consecutive targets, so a read copies slices, not bytes: (first k, last k + 1, target
            # of the first or -1 for bytes that read 0: the data area itself, or past the table)
            runs: list[list[int]] = []
            size = len(self.mem)
            for k, t in enumerate(self._targets):
                t = t if t < size and not d0 <= t < d0 + n else -1
                last = runs[-1] if runs else None
                if last is not None and last[1] == k and (
                        (t == -1 and last[2] == -1) or (t != -1 and last[2] != -1 and t == last[2] + k - last[0])):
                    last[1] = k + 1
                else:
                    runs.append([k, k + 1, t])
            self._runs = [tuple(r) for r in runs]
            self._gathers: dict[tuple[int, int], list[tuple[int, int]]] = {}

    def _indirect_overlap(self, addr: int, length: int) -> bool:
        ind = self.indirect
        return ind is not None and addr < ind[1] + ind[2] and addr + length > ind[1]

    def get(self, name: str) -> int:
        """Raw value of a control-table item (present items brought up to date first)."""
        it = self.table.item(name)
        if self._indirect_overlap(it.addr, it.size):
            return it.decode(self.read_block(it.addr, it.size)[1])
        self._advance()  # present items, and a Bus Watchdog that is due
        return it.decode(self.mem[it.addr: it.addr + it.size])

    def set(self, name: str, raw: int) -> None:
        """Set an item's raw value directly, bypassing access rules (set-up and tests; ID/baud apply at once)."""
        it = self.table.item(name)
        it.check(raw)
        self._advance()
        self.mem[it.addr: it.addr + it.size] = it.encode(raw)
        self._after_write(frozenset((it.addr,)))

    @property
    def status_return_level(self) -> int:
        return self.mem[STATUS_RETURN_LEVEL]

    @property
    def return_delay_s(self) -> float:
        return self.mem[RETURN_DELAY] * 2e-6

    @property
    def torque_enabled(self) -> bool:
        return bool(self.mem[TORQUE_ENABLE])

    @property
    def hardware_error(self) -> int:
        return self.mem[HARDWARE_ERROR]

    @property
    def alert(self) -> int:
        return P.ALERT if self.mem[HARDWARE_ERROR] else 0

    # -------------------------------------------------------------- horn and frames
    @property
    def angle(self) -> float:
        """Horn angle θ (rad around the centre tick)."""
        self._advance()
        return self._theta

    @angle.setter
    def angle(self, theta: float) -> None:
        self._advance()
        self._theta = float(theta)
        self._omega = self._torque = 0.0
        self._refresh()

    @property
    def q(self) -> float:
        """The horn angle as a joint position, through the mounting."""
        return self.mount.joint(self.angle)

    def goal_angle(self) -> float:
        """Goal Position as a horn angle (rad)."""
        return self._s * (_I32.unpack_from(self.mem, GOAL_POSITION)[0] - CENTRE - self._homing) * RAD_PER_TICK

    def profile_speed(self) -> float:
        """Profile Velocity as horn speed (rad/s); 0 = unlimited."""
        return _I32.unpack_from(self.mem, PROFILE_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT

    def set_present(self, theta: float, omega: float, torque: float) -> None:
        """Horn state from outside (simulation): angle (rad), speed (rad/s), torque (N·m)."""
        self._theta, self._omega, self._torque = theta, omega, torque
        self._t = self.clock()
        self._refresh()

    def _refresh(self) -> None:
        """Present items from the horn state."""
        mem, s = self.mem, self._s
        pos = CENTRE + s * round(self._theta / RAD_PER_TICK) + self._homing
        vel = s * round(self._omega / RAD_S_PER_VELOCITY_UNIT)
        if self._kt is not None:
            cur = round(s * self._torque / self._kt / self._current_unit)
        else:
            cur = round(s * 1000.0 * self._torque / self.datasheet.stall_torque)
        _PRESENT.pack_into(mem, PRESENT_CURRENT, max(-32768, min(32767, cur)), vel, max(-2**31, min(2**31 - 1, pos)))
        mem[MOVING] = 1 if abs(vel) > self._moving_threshold else 0
        _U16.pack_into(mem, REALTIME_TICK, int((self._t - self._t0) * 1000.0) & 0x7FFF)

    # -------------------------------------------------------------- standalone dynamics
    def _advance(self) -> None:
        """Bring the horn to now and refresh the present items (a simulated horn is published instead)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        if not self.external:
            self._integrate()
            self._refresh()

    # -------------------------------------------------------------- Bus Watchdog
    def heard(self) -> None:
        """An instruction packet for this servo (its ID or broadcast) arrived: the Bus Watchdog restarts
        (after a trip that was already due, which a late packet does not undo)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        self._last_rx = self.clock()

    def check_watchdog(self, now: float | None = None) -> float | None:
        """Trip the Bus Watchdog if it is due (module doc). Returns the time from the last packet to the
        trip when it trips now, else None. A standalone horn is integrated up to the trip instant."""
        wd = self.mem[BUS_WATCHDOG]
        if not 1 <= wd <= 127 or not self.mem[TORQUE_ENABLE]:
            return None
        now = self.clock() if now is None else now
        due = self._last_rx + wd * WATCHDOG_UNIT_S
        if now < due:
            return None
        if not self.external:
            self._integrate(due)  # the horn moved under its last goal until the trip
        mem = self.mem
        pos = CENTRE + self._s * round(self._theta / RAD_PER_TICK) + self._homing
        _I32.pack_into(mem, GOAL_POSITION, pos)  # stop: hold where it is
        _I32.pack_into(mem, GOAL_VELOCITY, 0)
        if not self.external:
            self._theta = self._s * (pos - CENTRE - self._homing) * RAD_PER_TICK
            self._omega = self._torque = 0.0
        mem[BUS_WATCHDOG] = WATCHDOG_ERROR
        self.revision += 1
        return (due if not self.external else now) - self._last_rx

    @property
    def watchdog_tripped(self) -> bool:
        return self.mem[BUS_WATCHDOG] == WATCHDOG_ERROR

    def _integrate(self, until: float | None = None) -> None:
        """Standalone dynamics: exact integration over the time elapsed since the last access (or up to
        ``until``)."""
        now = self.clock() if until is None else until
        dt = now - self._t
        self._t = now
        if self.external or dt <= 0.0:
            return
        mem = self.mem
        mode = mem[OPERATING_MODE]
        if not mem[TORQUE_ENABLE] or mode not in POSITION_MODES and mode != 1:
            self._omega = self._torque = 0.0
            return
        vmax = self.datasheet.no_load_speed
        if mode == 1:
            target = self._s * _I32.unpack_from(mem, GOAL_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT
            self._velocity_step(max(-vmax, min(vmax, target)), dt)
            return
        goal = self.goal_angle()
        if self._theta == goal and not self._omega:
            self._torque = 0.0
            return  # at rest on the goal
        profile = self.profile_speed()
        if 0.0 < profile < vmax:
            vmax = profile
        self._position_step(goal, vmax, dt)

    def _position_step(self, goal: float, vmax: float, dt: float) -> None:
        e = goal - self._theta
        band = vmax * TAU_S  # error below which the first-order law is not rate-limited
        sign = 1.0 if e >= 0 else -1.0
        if abs(e) > band:
            t1 = (abs(e) - band) / vmax
            if dt <= t1:
                e -= sign * vmax * dt
                self._omega = sign * vmax
                self._theta = goal - e
                self._torque = self._stiff_torque(e)
                return
            e, dt = sign * band, dt - t1
        e *= math.exp(-dt / TAU_S)
        if abs(e) < 1e-9:  # arrived (far below a tick): rest exactly on the goal
            e = 0.0
        self._theta = goal - e
        self._omega = e / TAU_S
        self._torque = self._stiff_torque(e)

    def _velocity_step(self, target: float, dt: float) -> None:
        k = math.exp(-dt / TAU_S)
        self._theta += target * dt + (self._omega - target) * TAU_S * (1.0 - k)
        self._omega = target + (self._omega - target) * k
        stall = self.datasheet.stall_torque
        self._torque = stall * (target - self._omega) / max(self.datasheet.no_load_speed, 1e-9)

    def _stiff_torque(self, error: float) -> float:
        stall = self.datasheet.stall_torque
        return max(-stall, min(stall, self._kp * error))

    # -------------------------------------------------------------- hardware errors
    def raise_hardware_error(self, bits_or_names: int | str | Iterable[str | int]) -> None:
        """Set Hardware Error Status bits; a bit in Shutdown turns torque off until REBOOT."""
        bits = hardware_bits(bits_or_names)
        self._advance()
        self.mem[HARDWARE_ERROR] |= bits
        if bits & self.mem[SHUTDOWN]:
            self._latched = True
            self.mem[TORQUE_ENABLE] = 0
            self._omega = self._torque = 0.0
            self._refresh()
        self.revision += 1

    # -------------------------------------------------------------- instructions
    def handle(self, packet: P.Packet | bytes) -> list[bytes]:
        """Run one instruction packet (or raw bytes holding packets) against this servo alone."""
        packets = P.PacketReader().feed(packet) if isinstance(packet, bytes | bytearray) else [packet]
        return [r for pkt in packets for _, r in dispatch([self], pkt)]

    def answers(self, inst: int) -> bool:
        """Whether the Status Return Level lets this servo answer ``inst``."""
        level = self.mem[STATUS_RETURN_LEVEL]
        return inst == P.PING or level >= 2 or (level == 1 and inst in READS)

    def direct(self, pkt: P.Packet) -> bytes | None:
        """A packet to this servo's ID, or a broadcast other than a group instruction: the status it sends."""
        rid, alert, inst = self.id, self.alert, pkt.inst
        reply = self.answers(inst) and (pkt.id != P.BROADCAST_ID or inst == P.PING)
        if not pkt.crc_ok:
            return status_packet(rid, P.CRC_ERROR | alert) if reply else None
        handler = _HANDLERS.get(inst)
        err, data = (P.INSTRUCTION_ERROR, b"") if handler is None else handler(self, pkt.params)
        return status_packet(rid, err | alert, data) if reply else None

    def _ping(self, params: bytes) -> tuple[int, bytes]:
        return 0, bytes((self.table.model_number & 0xFF, self.table.model_number >> 8, self.firmware))

    def _read(self, params: bytes) -> tuple[int, bytes]:
        if len(params) != 4:
            return P.DATA_LENGTH_ERROR, b""
        addr, length = params[0] | params[1] << 8, params[2] | params[3] << 8
        return self.read_block(addr, length)

    def read_block(self, addr: int, length: int) -> tuple[int, bytes]:
        """(error, data) of a read of ``length`` bytes at ``addr`` (data empty on error)."""
        if length <= 0:
            return P.DATA_LENGTH_ERROR, b""
        mem = self.mem
        if addr + length > len(mem):
            return P.DATA_RANGE_ERROR, b""
        if addr + length > DYNAMIC_START or mem[BUS_WATCHDOG]:
            self._advance()
        if not self._indirect_overlap(addr, length):
            return 0, bytes(mem[addr: addr + length])
        plan = self._gathers.get((addr, length))
        if plan is None:
            plan = self._gathers[(addr, length)] = self._gather_plan(addr, length)
        return 0, b"".join([mem[a:b] if a >= 0 else bytes(b) for a, b in plan])

    def _gather_plan(self, addr: int, length: int) -> list[tuple[int, int]]:
        """Slices of memory that make up a read overlapping the Indirect Data area, in order: (start, end)
        of memory, or (-1, n) for n bytes that read 0 (the data area itself, or past the table)."""
        d0, n = self.indirect[1], self.indirect[2]
        plan: list[tuple[int, int]] = []
        if addr < d0:
            plan.append((addr, d0))
        lo, hi = max(addr, d0) - d0, min(addr + length, d0 + n) - d0  # Indirect Data indices read
        for k0, k1, t in self._runs:
            a, b = max(k0, lo), min(k1, hi)
            if a < b:
                plan.append((t + a - k0, t + b - k0) if t >= 0 else (-1, b - a))
        if addr + length > d0 + n:
            plan.append((d0 + n, addr + length))
        return plan

    def _write_inst(self, params: bytes) -> tuple[int, bytes]:
        if len(params) < 3:
            return P.DATA_LENGTH_ERROR, b""
        return self.write(params[0] | params[1] << 8, params[2:]), b""

    def _reg_write(self, params: bytes) -> tuple[int, bytes]:
        if len(params) < 3:
            return P.DATA_LENGTH_ERROR, b""
        addr, data = params[0] | params[1] << 8, bytes(params[2:])
        err, _ = self._check_write(addr, data)
        if not err:
            self._registered = (addr, data)
            self.mem[REGISTERED] = 1
        return err, b""

    def _action(self, params: bytes) -> tuple[int, bytes]:
        if self._registered is None:
            return P.INSTRUCTION_ERROR, b""
        addr, data = self._registered
        self._registered = None
        self.mem[REGISTERED] = 0
        return self.write(addr, data), b""

    def _reboot(self, params: bytes) -> tuple[int, bytes]:
        self._advance()
        mem = self.mem
        fresh = self.table.defaults()
        fresh[:EEPROM_END] = mem[:EEPROM_END]
        self._boot(fresh, mem[ID], mem[BAUD])
        return 0, b""

    def _factory_reset(self, params: bytes) -> tuple[int, bytes]:
        if len(params) != 1:
            return P.DATA_LENGTH_ERROR, b""
        option = params[0]
        if option not in (0xFF, 0x01, 0x02):
            return P.DATA_RANGE_ERROR, b""
        if self.mem[TORQUE_ENABLE]:
            return P.ACCESS_ERROR, b""
        self._advance()
        dxl_id = self.id if option in (0x01, 0x02) else 1
        baud = self.mem[BAUD] if option == 0x02 else self.table.item("baud_rate").default
        self._boot(self.table.defaults(), dxl_id, baud)  # the reply was addressed before: old ID, old baud
        return 0, b""

    def _clear(self, params: bytes) -> tuple[int, bytes]:
        if bytes(params[:5]) == CLEAR_MULTI_TURN and self.mem[OPERATING_MODE] == 4:
            self._advance()
            self._theta = math.remainder(self._theta, 2.0 * math.pi)
            self._refresh()
        return 0, b""

    # -------------------------------------------------------------- writes
    def _check_write(self, addr: int, data: bytes) -> tuple[int, bytearray | None]:
        """(error, candidate memory) for a write; the candidate holds the written items."""
        plan = _write_plan(self.table, addr, len(data))
        if plan.error:
            return plan.error, None
        mem = self.mem
        if plan.eeprom and mem[TORQUE_ENABLE]:
            return P.ACCESS_ERROR, None
        cand = bytearray(mem)
        for it, off in plan.items:
            raw = data[off: off + it.size]
            v = int.from_bytes(raw, "little", signed=it.signed)
            if not it.lo <= v <= it.hi or (it.values is not None and v not in it.values):
                return P.DATA_RANGE_ERROR, None
            cand[it.addr: it.addr + it.size] = raw
        return self._check_limits(cand, plan.addrs), cand

    def _check_limits(self, cand: bytearray, addrs: frozenset[int]) -> int:
        if GOAL_POSITION in addrs and cand[OPERATING_MODE] == 3:
            goal = _I32.unpack_from(cand, GOAL_POSITION)[0]
            lo, hi = _I32.unpack_from(cand, MIN_POSITION)[0], _I32.unpack_from(cand, MAX_POSITION)[0]
            if not lo <= goal <= hi:
                return P.DATA_LIMIT_ERROR
        if GOAL_VELOCITY in addrs and abs(_I32.unpack_from(cand, GOAL_VELOCITY)[0]) > _I32.unpack_from(
                cand, VELOCITY_LIMIT)[0]:
            return P.DATA_LIMIT_ERROR
        if GOAL_CURRENT in addrs and self.table.at(CURRENT_LIMIT) is not None and abs(
                struct.unpack_from("<h", cand, GOAL_CURRENT)[0]) > _U16.unpack_from(cand, CURRENT_LIMIT)[0]:
            return P.DATA_LIMIT_ERROR
        if TORQUE_ENABLE in addrs and cand[TORQUE_ENABLE] and self._latched:
            return P.RESULT_FAIL
        if self.mem[BUS_WATCHDOG] == WATCHDOG_ERROR and (addrs & GOALS or (BUS_WATCHDOG in addrs
                                                                           and cand[BUS_WATCHDOG])):
            return P.DATA_RANGE_ERROR  # tripped: goals refused, and the watchdog takes only 0 (clear) first
        return 0

    def write(self, addr: int, data: bytes) -> int:
        """Apply a WRITE of ``data`` at ``addr`` by the instruction rules; returns the status error (0 = ok).

        Bytes that fall on Indirect Data go to the addresses they stand for; the write is checked whole
        (every part) before any part is applied."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        self._integrate()  # the time so far ran under the old goal; present items refresh at the next read
        runs = self._indirect_runs(addr, data) if self._indirect_overlap(addr, len(data)) else [(addr, data)]
        checked = []
        for a, d in runs:
            err, cand = self._check_write(a, d)
            if err:
                return err
            checked.append((_write_plan(self.table, a, len(d)), cand))
        mem = self.mem
        for plan, cand in checked:
            for it, _ in plan.items:
                mem[it.addr: it.addr + it.size] = cand[it.addr: it.addr + it.size]
            self._after_write(plan.addrs)
        return 0

    def _indirect_runs(self, addr: int, data: bytes) -> list[tuple[int, bytes]]:
        """A write split into runs of consecutive target addresses (Indirect Data bytes redirected)."""
        d0, n = self.indirect[1], self.indirect[2]
        runs: list[tuple[int, bytearray]] = []
        for k, byte in enumerate(data):
            a = addr + k
            t = self._targets[a - d0] if d0 <= a < d0 + n else a
            if runs and runs[-1][0] + len(runs[-1][1]) == t:
                runs[-1][1].append(byte)
            else:
                runs.append((t, bytearray((byte,))))
        return [(a, bytes(b)) for a, b in runs]

    def _after_write(self, addrs: frozenset[int]) -> None:
        mem = self.mem
        self.revision += 1
        if BAUD in addrs:
            self.baud_bps = BAUD_RATES[mem[BAUD]]
        if TORQUE_ENABLE in addrs:
            if not mem[TORQUE_ENABLE]:
                self._omega = self._torque = 0.0
            elif self.torque_on_at is None:
                self.torque_on_at = self.clock()
        if BUS_WATCHDOG in addrs:
            self._last_rx = self.clock()  # the write itself is a packet: the time-out counts from it
        if self.indirect is not None and any(self.indirect[0] <= a < self.indirect[0] + 2 * self.indirect[2]
                                             for a in addrs):
            self._map_indirect()
        if addrs & _CACHED:
            self._cache_settings()
            self._refresh()  # a new Homing Offset or Drive Mode shows in Present Position at once
        if ID in addrs:
            self.id = mem[ID]

    def __repr__(self) -> str:
        return f"VirtualServo({self.model!r}, id={self.id}, baud_bps={self.baud_bps})"


_HANDLERS: dict[int, Callable[[VirtualServo, bytes], tuple[int, bytes]]] = {
    P.PING: VirtualServo._ping, P.READ: VirtualServo._read, P.WRITE: VirtualServo._write_inst,
    P.REG_WRITE: VirtualServo._reg_write, P.ACTION: VirtualServo._action, P.REBOOT: VirtualServo._reboot,
    P.FACTORY_RESET: VirtualServo._factory_reset, P.CLEAR: VirtualServo._clear,
}


# ----------------------------------------------------------------------------------------- dispatch
Reply = tuple[float, bytes]  # (the replying servo's return delay in s, status packet)


def dispatch(servos: Sequence[VirtualServo], pkt: P.Packet) -> list[Reply]:
    """The replies the listening ``servos`` send to one instruction packet, in wire order.

    Never raises on any packet. Every reply is a complete, valid status packet, except that a fast
    read whose list names an absent servo gives a packet short of its announced length (module doc).
    """
    if pkt.crc_ok:  # the Bus Watchdog counts every instruction a servo hears: its own ID or broadcast
        for s in servos:
            if pkt.id == s.id or pkt.id == P.BROADCAST_ID:
                s.heard()
    if pkt.id != P.BROADCAST_ID:
        return _collide([(s.return_delay_s, r) for s in servos if s.id == pkt.id and (r := s.direct(pkt)) is not None])
    if not pkt.crc_ok:
        return []
    inst = pkt.inst
    if inst in GROUP_READS:
        return _group_read(servos, pkt)
    if inst in GROUP_WRITES:
        _group_write(servos, pkt)
        return []
    replies = [(s.id, s.return_delay_s, r) for s in servos if (r := s.direct(pkt)) is not None]
    replies.sort(key=lambda x: x[0])  # broadcast PING: ascending ID
    out: list[Reply] = []
    for _, same in itertools.groupby(replies, key=lambda x: x[0]):  # each ID answers in its own slot
        out += _collide([(d, r) for _, d, r in same])
    return out


def _collide(replies: list[Reply]) -> list[Reply]:
    """Servos sharing an ID answer in the same slot and drive the wire at once.

    The half-duplex line reads low while any transmitter drives it low (wired-AND); their start bits
    are modelled one byte apart, so the client receives ``a[k] & b[k−1]``: a garbled packet whose CRC
    fails, as on a real bus with two servos on one ID. One reply passes unchanged.
    """
    if len(replies) < 2:
        return replies
    data = bytearray(replies[0][1])
    for skew, (_, r) in enumerate(replies[1:], start=1):
        shifted = b"\xff" * skew + r
        data += b"\xff" * max(0, len(shifted) - len(data))
        for k, byte in enumerate(shifted):
            data[k] &= byte
    return [(replies[0][0], bytes(data))]


def _group_read(servos: Sequence[VirtualServo], pkt: P.Packet) -> list[Reply]:
    p, inst = pkt.params, pkt.inst
    by_id = {s.id: s for s in servos}
    if inst in (P.SYNC_READ, P.FAST_SYNC_READ):
        if len(p) < 5:
            return []
        addr, length = p[0] | p[1] << 8, p[2] | p[3] << 8
        requests = [(i, addr, length) for i in p[4:]]
    else:
        requests = [(p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8) for k in range(0, len(p) - 4, 5)]
        if not requests or len(p) % 5:
            return []
    fast = inst in (P.FAST_SYNC_READ, P.FAST_BULK_READ)
    announced = sum(4 + length for _, _, length in requests)
    if fast and announced + 3 > P.MAX_PACKET:
        return []
    out: list[Reply] = []
    segments: list[tuple[int, int, bytes]] = []
    delay = None
    for dxl_id, addr, length in requests:
        s = by_id.get(dxl_id)
        if s is None or s.mem[STATUS_RETURN_LEVEL] == 0 or (fast and s.firmware < FAST_SYNC_READ_MIN_FIRMWARE):
            continue
        err, data = s.read_block(addr, length)
        if fast:
            segments.append((dxl_id, err | s.alert, data if not err else bytes(length)))
            delay = s.return_delay_s if delay is None else delay
        else:
            out.append((s.return_delay_s, status_packet(dxl_id, err | s.alert, data)))
    if fast and segments:
        return [(delay or 0.0, fast_packet(announced, segments))]
    return out


def _group_write(servos: Sequence[VirtualServo], pkt: P.Packet) -> None:
    p = pkt.params
    by_id = {s.id: s for s in servos}
    writes: list[tuple[int, int, bytes]] = []
    if pkt.inst == P.SYNC_WRITE:
        if len(p) < 4:
            return
        addr, length = p[0] | p[1] << 8, p[2] | p[3] << 8
        step = 1 + length
        if length == 0 or (len(p) - 4) % step:
            return
        writes = [(p[k], addr, p[k + 1: k + step]) for k in range(4, len(p), step)]
    else:
        k = 0
        while k < len(p):
            if k + 5 > len(p):
                return
            length = p[k + 3] | p[k + 4] << 8
            if k + 5 + length > len(p):
                return
            writes.append((p[k], p[k + 1] | p[k + 2] << 8, p[k + 5: k + 5 + length]))
            k += 5 + length
    for dxl_id, addr, data in writes:
        s = by_id.get(dxl_id)
        if s is not None:
            s.write(addr, bytes(data))


# ----------------------------------------------------------------------------------------- faults
@dataclass
class Faults:
    """Injected faults (module doc). Rates and delay may be changed while the bus runs."""

    drop: float = 0.0  # fraction of replies lost
    corrupt: float = 0.0  # fraction of replies with one byte flipped
    delay_ms: float = 0.0  # extra delay before the replies to each request
    remove: tuple[int, ...] = ()  # servo IDs absent from the start
    hwerror: dict[int, int] = field(default_factory=dict)  # ID -> Hardware Error Status bits raised at start
    close_after: float | None = None  # s after start() at which the port vanishes
    seed: int | None = None  # overrides the bus's seed
    reboot: tuple[tuple[int, float], ...] = ()  # (ID, s after its torque first came on): a brown-out reboot
    torque_off: tuple[tuple[int, float], ...] = ()  # (ID, s after torque first came on): switched off elsewhere

    def __post_init__(self):
        for name in ("drop", "corrupt"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise ParameterError(f"faults: {name}={v!r} must be a fraction in 0…1")
        if not (isinstance(self.delay_ms, int | float) and 0.0 <= self.delay_ms <= 10_000):
            raise ParameterError(f"faults: delay_ms={self.delay_ms!r} must be in 0…10000 ms")
        if self.close_after is not None and not (isinstance(self.close_after, int | float) and self.close_after >= 0):
            raise ParameterError(f"faults: close_after={self.close_after!r} must be ≥ 0 s")
        self.remove = tuple(int(i) for i in self.remove)
        self.hwerror = {int(k): hardware_bits(v) for k, v in self.hwerror.items()}
        for name in ("reboot", "torque_off"):
            timed = tuple((int(i), float(t)) for i, t in getattr(self, name))
            for i, t in timed:
                if not (0 <= i <= P.MAX_ID and math.isfinite(t) and t >= 0):
                    raise ParameterError(f"faults: {name}={i}@{t} needs a servo ID and a time ≥ 0 s")
            setattr(self, name, timed)


_FAULT_KEYS = ("drop", "corrupt", "delay_ms", "remove", "hwerror", "close_after", "seed", "reboot", "torque_off")


def parse_faults(spec: str) -> Faults:
    """``"drop=0.01,corrupt=0.001,delay_ms=5,remove=3,hwerror=5:overload,close_after=2.5,seed=0"`` → `Faults`.

    ``remove`` and ``hwerror`` may repeat; several IDs or error names join with ``+``
    (``remove=3+4``, ``hwerror=5:overload+overheating``, ``hwerror=5:0x24``). ``reboot=ID@T`` (the servo
    reboots, as after a brown-out) and ``torque_off=ID@T`` (its torque is switched off, as from another
    program) act T s after torque first came on at that servo; both may repeat. Empty spec: no faults.
    """
    kw: dict[str, object] = {"remove": [], "hwerror": {}, "reboot": [], "torque_off": []}
    for part in (s.strip() for s in spec.split(",")):
        if not part:
            continue
        key, sep, value = (x.strip() for x in part.partition("="))
        if key not in _FAULT_KEYS:
            raise ParameterError(f"fault spec: unknown key {key!r}; known: {', '.join(_FAULT_KEYS)}")
        if not sep or not value:
            raise ParameterError(f"fault spec: {key!r} needs a value ({key}=…)")
        try:
            _parse_fault_value(kw, key, value)
        except ValueError:
            raise ParameterError(f"fault spec: bad value for {key!r}: {value!r}") from None
    for key in ("remove", "reboot", "torque_off"):
        kw[key] = tuple(kw[key])  # type: ignore[arg-type]
    try:
        return Faults(**kw)  # type: ignore[arg-type]
    except ParameterError as e:
        raise ParameterError(f"fault spec: {e}") from None


def _parse_fault_value(kw: dict, key: str, value: str) -> None:
    if key in ("drop", "corrupt", "delay_ms", "close_after"):
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(value)
        kw[key] = v
    elif key == "seed":
        kw[key] = int(value, 0)
    elif key == "remove":
        kw[key].extend(_servo_id(x) for x in value.split("+"))
    elif key in ("reboot", "torque_off"):
        sid, at, t = value.partition("@")
        seconds = float(t)
        if not at or not math.isfinite(seconds) or seconds < 0:
            raise ValueError(value)
        kw[key].append((_servo_id(sid), seconds))
    else:
        sid, colon, bits = value.partition(":")
        if not colon:
            raise ValueError(value)
        dxl_id = _servo_id(sid)
        kw[key][dxl_id] = kw[key].get(dxl_id, 0) | hardware_bits(bits)


def _servo_id(text: str) -> int:
    v = int(text.strip(), 0)
    if not 0 <= v <= P.MAX_ID:
        raise ValueError(text)
    return v


# ----------------------------------------------------------------------------------------- the bus
@dataclass
class BusStats:
    """Counters of a `VirtualBus` (read them any time; the server thread updates them)."""

    packets: int = 0  # instruction packets parsed
    replies: int = 0  # status packets written (a fast read's one packet counts once)
    dropped: int = 0  # replies dropped by fault injection
    corrupted: int = 0  # replies corrupted by fault injection
    crc_errors: int = 0  # packets received with a bad CRC
    garbage_bytes: int = 0  # bytes discarded by the parser (noise, partial packets after a gap)
    baud_mismatch: int = 0  # packets no servo heard because none listens at the client's baud
    overflows: int = 0  # replies (partly) lost because the client did not read and the pty was full
    sim_lag_s: float = 0.0  # simulated time skipped because the simulation fell behind the wall clock
    instructions: collections.Counter = field(default_factory=collections.Counter)  # name -> count
    watchdog_trips: list = field(default_factory=list)  # (servo ID, s from its last packet to the trip)
    timed_faults: list = field(default_factory=list)  # (kind, servo ID) of the reboot/torque_off faults applied

    def as_dict(self) -> dict[str, object]:
        d = {k: v for k, v in self.__dict__.items() if k != "instructions"}
        d["instructions"] = dict(self.instructions)
        return d

    def summary(self) -> str:
        inst = ", ".join(f"{k} {v}" for k, v in sorted(self.instructions.items()))
        return (f"{self.packets} packets ({inst or 'none'}), {self.replies} replies, {self.dropped} dropped, "
                f"{self.corrupted} corrupted, {self.crc_errors} CRC errors, {self.garbage_bytes} garbage bytes, "
                f"{self.baud_mismatch} at a baud no servo uses, {self.overflows} overflows"
                + (f", simulation lagged {self.sim_lag_s:.3f} s" if self.sim_lag_s else "")
                + ("; bus watchdog tripped: " + ", ".join(f"ID {i} after {dt:.3f} s" for i, dt in self.watchdog_trips)
                   if self.watchdog_trips else "")
                + ("; faults applied: " + ", ".join(f"{k} ID {i}" for k, i in self.timed_faults)
                   if self.timed_faults else ""))


def client_baud(master_fd: int, buf: bytearray | None = None) -> int | None:
    """The baud rate the client set on the pty's slave side, read through the master (None if unknown)."""
    buf = buf if buf is not None else bytearray(_TERMIOS2.size)
    try:
        fcntl.ioctl(master_fd, _TCGETS2, buf)
        ospeed = _TERMIOS2.unpack_from(buf)[-1]
        if ospeed:
            return ospeed
    except OSError:
        pass
    try:
        speed = termios.tcgetattr(master_fd)[5]
    except termios.error:
        return None
    return None if speed == _BOTHER else _B_RATES.get(speed)


class VirtualBus:
    """Servos on a pseudo-terminal (module doc). ``bus.port`` is the device path a client opens.

    Args:
        servos: the servos on the bus (more with `add_servo`).
        wire_time: model the wire's timing (module doc); may be changed while running.
        faults: a `Faults` or a spec string for `parse_faults`.
        seed: seed of the fault RNG (``Faults.seed`` overrides it).

    ``start()`` / ``stop()`` or ``with VirtualBus(...) as bus:``; ``stop()`` joins every thread
    and closes every file descriptor.
    """

    def __init__(self, servos: Iterable[VirtualServo] = (), *, wire_time: bool = False,
                 faults: Faults | str | None = None, seed: int = 0):
        self.wire_time = wire_time
        self.faults = parse_faults(faults) if isinstance(faults, str) else (faults or Faults())
        self.seed = seed
        self.rng = random.Random(self.faults.seed if self.faults.seed is not None else seed)
        self.stats = BusStats()
        self.lock = threading.RLock()
        self._servos: list[VirtualServo] = []
        self._removed: set[int] = set()  # id(servo) of removed servos
        self._listening: list[VirtualServo] = []
        for s in servos:
            self.add_servo(s)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self.imu_port: str | None = None
        self._fds_lock = threading.Lock()
        self._fds_open = True
        self._wake_r, self._wake_w = os.pipe()
        self._halt = False
        self._server: threading.Thread | None = None
        self._started = False
        self._stopped = False
        self._bus_free = 0.0
        self._due: list[tuple[float, int, bytes, int]] = []  # scheduled replies: (time, seq, bytes, count)
        self._seq = itertools.count()
        self._close_deadline: float | None = None
        self._timed: list[tuple[str, int, float]] = []  # reboot/torque_off faults still to apply
        self._tc_buf = bytearray(_TERMIOS2.size)
        self.spec: RobotSpec | None = None  # set by for_robot
        self.sim: _SimBackend | None = None  # set by for_robot(sim=True)

    # -------------------------------------------------------------- servos
    def add_servo(self, servo: VirtualServo) -> VirtualServo:
        with self.lock:
            self._servos.append(servo)
            self._relist()
        return servo

    def _relist(self) -> None:
        self._listening = [s for s in self._servos if id(s) not in self._removed]

    @property
    def servos(self) -> list[VirtualServo]:
        """Every servo, removed ones included, in the order added."""
        return list(self._servos)

    def servo(self, dxl_id: int) -> VirtualServo:
        """The servo with this ID (present or removed)."""
        for s in self._servos:
            if s.id == dxl_id:
                return s
        raise ParameterError(f"virtual bus has no servo with ID {dxl_id}; IDs: "
                             f"{', '.join(str(s.id) for s in self._servos) or 'none'}")

    def remove_servo(self, dxl_id: int | VirtualServo) -> None:
        """The servo vanishes from the bus (unplugged): it neither hears nor answers until `restore_servo`.

        Takes an ID or the `VirtualServo` itself (needed when several servos share an ID, as factory-new
        ones do).
        """
        with self.lock:
            self._removed.add(id(self._find(dxl_id)))
            self._relist()

    def restore_servo(self, dxl_id: int | VirtualServo) -> None:
        """Plug a removed servo back in (by ID or the `VirtualServo` itself)."""
        with self.lock:
            self._removed.discard(id(self._find(dxl_id)))
            self._relist()

    def _find(self, servo: int | VirtualServo) -> VirtualServo:
        if isinstance(servo, VirtualServo):
            if not any(s is servo for s in self._servos):
                raise ParameterError(f"{servo!r} is not on this virtual bus")
            return servo
        return self.servo(servo)

    def raise_hardware_error(self, dxl_id: int, bits_or_names: int | str | Iterable[str | int]) -> None:
        """Set Hardware Error Status bits on a servo (``"overload"``, ``["overheating", "overload"]``, 0x20)."""
        with self.lock:
            self.servo(dxl_id).raise_hardware_error(bits_or_names)

    def set_faults(self, faults: Faults | str) -> None:
        """Replace the faults; removals, hardware errors and close_after take effect now if running."""
        faults = parse_faults(faults) if isinstance(faults, str) else faults
        with self.lock:
            self.faults = faults
            if faults.seed is not None:
                self.rng = random.Random(faults.seed)
            if self._started:
                self._apply_start_faults()

    def _apply_start_faults(self) -> None:
        f = self.faults
        for dxl_id in f.remove:
            self.remove_servo(dxl_id)
        for dxl_id, bits in f.hwerror.items():
            self.raise_hardware_error(dxl_id, bits)
        if f.close_after is not None:
            self._close_deadline = time.perf_counter() + f.close_after
            self._wake()
        self._timed = [("reboot", i, t) for i, t in f.reboot] + [("torque_off", i, t) for i, t in f.torque_off]
        for _, i, _ in self._timed:
            self.servo(i)  # an unknown ID is one line now, not a silent no-op later

    def housekeeping(self) -> None:
        """What happens on the servos' own clocks, between packets: Bus Watchdog trips and timed faults
        (called by the server thread and the simulation thread, bus lock held)."""
        for s in self._listening:
            if s.mem[BUS_WATCHDOG] and not s.watchdog_tripped:
                delay = s.check_watchdog()
                if delay is not None:
                    self.stats.watchdog_trips.append((s.id, delay))
        if self._timed:
            left = []
            for kind, i, t in self._timed:
                s = self.servo(i)
                if s.torque_on_at is None or s.clock() - s.torque_on_at < t:
                    left.append((kind, i, t))
                elif kind == "reboot":
                    s._reboot(b"")
                    self.stats.timed_faults.append((kind, i))
                else:
                    s.set("torque_enable", 0)
                    self.stats.timed_faults.append((kind, i))
            self._timed = left

    def _busy(self) -> bool:
        """Something on the servos' clocks is pending (an armed Bus Watchdog, a timed fault)."""
        return bool(self._timed) or any(s.mem[BUS_WATCHDOG] and s.mem[TORQUE_ENABLE] and not s.watchdog_tripped
                                        for s in self._listening)

    # -------------------------------------------------------------- dispatch
    def dispatch(self, pkt: P.Packet | bytes, baud: int | None = None) -> list[bytes]:
        """The status packets the servos send back to one packet (no faults, no I/O); for tests."""
        packets = P.PacketReader().feed(pkt) if isinstance(pkt, bytes | bytearray) else [pkt]
        out = []
        for p in packets:
            with self.lock:
                out += [r for _, r in dispatch(self._hearing(baud), p)]
        return out

    def _hearing(self, baud: int | None) -> list[VirtualServo]:
        if baud is None:
            return self._listening
        return [s for s in self._listening if s.baud_bps == baud]

    # -------------------------------------------------------------- lifecycle
    def start(self) -> VirtualBus:
        if self._stopped:
            raise RuntimeError("a stopped VirtualBus cannot be restarted")
        if self._started:
            return self
        self._started = True
        with self.lock:
            self._apply_start_faults()
        self._server = threading.Thread(target=self._serve_guarded, name=f"virtual-bus {self.port}", daemon=True)
        self._server.start()
        if self.sim is not None:
            self.sim.start()
        return self

    def stop(self) -> None:
        """Stop every thread, close the ports (idempotent)."""
        self._stopped = True
        self._halt_server()
        self._close_fds()
        if self.sim is not None:
            self.sim.stop()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def close_port(self) -> None:
        """The port vanishes (pty closed): clients get I/O errors, as when a USB adapter is unplugged."""
        self._halt_server()
        self._close_fds()

    def __enter__(self) -> VirtualBus:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def port_open(self) -> bool:
        return self._fds_open

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def _halt_server(self) -> None:
        self._halt = True
        self._wake()
        if self._server is not None and self._server is not threading.current_thread():
            self._server.join(timeout=5.0)

    def _close_fds(self) -> None:
        with self._fds_lock:
            if self._fds_open:
                self._fds_open = False
                for fd in (self._master, self._slave):
                    with contextlib.suppress(OSError):
                        os.close(fd)

    # -------------------------------------------------------------- server thread
    def _serve_guarded(self) -> None:
        try:
            self._serve()
        except Exception as e:  # noqa: BLE001 - a server bug must not hang clients: report and close the port
            print(f"virtual bus: server stopped: {type(e).__name__}: {e}", file=sys.stderr)
            self._close_fds()

    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        reader = P.PacketReader()
        last_byte = last_housekeeping = 0.0
        while not self._halt:
            self._flush_due()
            with self.lock:
                t = time.perf_counter()
                if t - last_housekeeping >= HOUSEKEEPING_S:  # not after every packet of a busy bus
                    self.housekeeping()
                    last_housekeeping = t
                busy = self._busy()
            timeout = self._poll_timeout(reader.pending, last_byte)
            events = poller.poll(min(timeout, 5) if busy else timeout)
            now = time.perf_counter()
            if self._close_deadline is not None and now >= self._close_deadline:
                self._close_fds()
                return
            got = False
            for fd, ev in events:
                if fd == self._wake_r:
                    with contextlib.suppress(OSError):
                        os.read(self._wake_r, 4096)
                    continue
                if ev & (select.POLLERR | select.POLLNVAL):
                    return
                try:
                    data = os.read(self._master, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    return
                got, last_byte = True, now
                for pkt in reader.feed(data):
                    self._process(pkt, now)
            # The gap is judged by silence seen while waiting, not by when bytes are read: a server
            # thread that was starved of CPU must not tear a packet whose rest was already waiting.
            if not got and reader.pending and time.perf_counter() - last_byte >= GAP_S:
                reader.reset()
            self.stats.garbage_bytes = reader.dropped

    def _poll_timeout(self, pending: int, last_byte: float) -> int:
        """Milliseconds poll may sleep: until a partial packet expires, the port closes, or (less the spin
        margin, rounded down) the next scheduled reply is due."""
        now = time.perf_counter()
        ms = 1000
        if pending:
            ms = min(ms, math.ceil((last_byte + GAP_S - now) * 1000.0))
        if self._close_deadline is not None:
            ms = min(ms, math.ceil((self._close_deadline - now) * 1000.0))
        if self._due:
            ms = min(ms, math.floor((self._due[0][0] - SPIN_S - now) * 1000.0))
        return max(0, ms)

    def _process(self, pkt: P.Packet, t_rx: float) -> None:
        stats = self.stats
        stats.packets += 1
        stats.instructions[P.INSTRUCTIONS.get(pkt.inst, f"0x{pkt.inst:02X}")] += 1
        if not pkt.crc_ok:
            stats.crc_errors += 1
        baud = client_baud(self._master, self._tc_buf)
        with self.lock:
            servos = self._hearing(baud)
            if not servos and self._listening:
                stats.baud_mismatch += 1
            replies = dispatch(servos, pkt) if servos else []
        if self.wire_time:
            self._emit_timed(len(pkt.raw), replies, t_rx, baud or 1_000_000)
        elif replies:
            self._emit(replies, t_rx)

    def _faulted(self, data: bytes) -> bytes | None:
        f, rng = self.faults, self.rng
        if f.drop and rng.random() < f.drop:
            self.stats.dropped += 1
            return None
        if f.corrupt and rng.random() < f.corrupt:
            b = bytearray(data)
            b[rng.randrange(len(b))] ^= rng.randrange(1, 256)
            self.stats.corrupted += 1
            return bytes(b)
        return data

    def _emit(self, replies: list[Reply], t_rx: float) -> None:
        """All replies to one packet in one write: now, or ``delay_ms`` after the request arrived."""
        out = [r for _, data in replies if (r := self._faulted(data)) is not None]
        if not out:
            return
        if self.faults.delay_ms:
            self._schedule(t_rx + self.faults.delay_ms / 1000.0, b"".join(out), len(out))
        else:
            self._write(b"".join(out), len(out))

    def _emit_timed(self, request_len: int, replies: list[Reply], t_rx: float, baud: int) -> None:
        """Wire-time mode: each reply is scheduled for when its last byte would arrive (module doc)."""
        byte_s = 10.0 / baud
        end = max(t_rx, self._bus_free) + request_len * byte_s
        if replies and self.faults.delay_ms:
            end += self.faults.delay_ms / 1000.0
        for delay, data in replies:
            end += delay + len(data) * byte_s
            out = self._faulted(data)
            if out is not None:
                self._schedule(end, out, 1)
        self._bus_free = end

    def _schedule(self, t: float, data: bytes, n_replies: int) -> None:
        heapq.heappush(self._due, (t, next(self._seq), data, n_replies))

    def _flush_due(self) -> None:
        """Write every scheduled reply due within the spin margin, each at its time (spinning on the clock)."""
        due = self._due
        while due:
            t = due[0][0]
            if t - time.perf_counter() > SPIN_S:
                return
            while time.perf_counter() < t:
                pass
            _, _, data, n = heapq.heappop(due)
            self._write(data, n)

    def _write(self, data: bytes, n_replies: int) -> None:
        self.stats.replies += n_replies  # counted first: a client may look as soon as the bytes arrive
        try:
            while data:
                n = os.write(self._master, data)
                data = data[n:]
        except BlockingIOError:
            self.stats.overflows += 1
        except OSError:  # the port was closed under us
            self.stats.replies -= n_replies

    # -------------------------------------------------------------- robots
    @classmethod
    def for_robot(cls, spec_or_name: RobotSpec | str, *, baud: int = 1_000_000, sim: bool = False,
                  wire_time: bool = False, faults: Faults | str | None = None, seed: int = 0,
                  mount_offsets: Mapping[str, float] | None = None,
                  servo_params: Mapping[str, object] | None = None, fixed_base: bool = False,
                  imu_mount: Sequence[float] | None = None, imu_drift: Sequence[float] | None = None,
                  drop: Sequence[float] | None = None) -> VirtualBus:
        """One servo per joint of a robot description (ID, model and mounting from it), at ``baud``,
        Return Delay Time 0, Min/Max Position Limit at the description's joint limits (as `felis check-eeprom`
        expects of a set-up robot). ``sim=True`` backs the servos with the
        MuJoCo model (and starts the cat's IMU on ``bus.imu_port`` when started).
        ``mount_offsets`` (joint -> rad) simulates an uncalibrated assembly. With ``sim=True``,
        ``servo_params`` (joint -> `felis.sim.servo.ServoParams`) replaces the datasheet servo model of
        those joints (e.g. deliberately wrong parameters for a system-identification test) and
        ``fixed_base`` hangs a floating-base robot on a stand (`felis.sim.robot.MujocoRobot`).
        ``imu_mount`` (unit quaternion w, x, y, z: the sensor in the body frame) and ``imu_drift``
        (sensor-frame rad/s, 3-vector) simulate a mis-mounted, drifting IMU (module doc; needs sim=True
        and a robot with an IMU). ``drop`` (height m, roll°, pitch°, yaw°) holds the robot in the air,
        turned, until torque first comes on (module doc; needs sim=True and the floating base).
        """
        spec = spec_or_name if isinstance(spec_or_name, RobotSpec) else load_spec(spec_or_name)
        if (servo_params or fixed_base) and not sim:
            raise ParameterError("servo parameters and a fixed base apply to the simulation: they need sim=True "
                                 "(--sim)")
        drop = check_drop(drop, sim=sim, fixed_base=fixed_base)
        imu_mount_model = None
        if imu_mount is not None or imu_drift is not None:
            if not sim or spec.sensors.imu is None:
                raise ParameterError("an IMU mount or drift needs the simulated IMU: sim=True (--sim) and a robot "
                                     f"with an IMU ({spec.name} {'has one' if spec.sensors.imu else 'has none'})")
            from felis.drivers.imu import SensorMount

            try:
                imu_mount_model = SensorMount(imu_mount, imu_drift)
            except ValueError as e:
                raise ParameterError(str(e)) from None
        offsets = dict(mount_offsets or {})
        unknown = sorted(set(offsets) - set(spec.names))
        if unknown:
            raise ParameterError(f"mount offset for unknown joint {unknown[0]!r}; joints: {', '.join(spec.names)}")
        servos = []
        for j in spec.joints:
            mount = Mount(j.direction, j.zero, j.m_per_rad, float(offsets.get(j.name, 0.0)))
            s = VirtualServo(j.servo, j.servo_id, baud, mount=mount)
            s.set("return_delay_time", 0)
            limits = sorted(CENTRE + round(Mount(j.direction, j.zero, j.m_per_rad).horn(q) / RAD_PER_TICK)
                            for q in (j.lower, j.upper))  # as a set-up robot holds them (felis check-eeprom)
            s.set("min_position_limit", max(0, limits[0]))
            s.set("max_position_limit", min(4095, limits[1]))
            s.angle = mount.horn(min(max(0.0, j.lower), j.upper))
            s.set("goal_position", s.get("present_position"))
            servos.append(s)
        bus = cls(servos, wire_time=wire_time, faults=faults, seed=seed)
        bus.spec = spec
        if sim:
            try:
                bus.sim = _SimBackend(bus, spec, servos, servo_params=servo_params, fixed_base=fixed_base,
                                      imu_mount=imu_mount_model, drop=drop)
            except BaseException:
                bus.stop()
                raise
        return bus


# ----------------------------------------------------------------------------------------- simulation
def check_drop(drop: Sequence[float] | None, *, sim: bool = True,
               fixed_base: bool = False) -> tuple[float, float, float, float] | None:
    """A drop (height m, roll°, pitch°, yaw°) as four floats, checked as `felis.sim.scenarios.drop` checks
    it (and that it can apply: the simulation, a floating base); None passes. ParameterError, one line."""
    if drop is None:
        return None
    from felis.sim.scenarios import MAX_DROP_HEIGHT

    try:
        values = tuple(float(v) for v in drop)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ParameterError(f"a drop is four finite numbers: height (m), roll, pitch, yaw (degrees), got {drop!r}")
    h, *angles = values
    if not 0.0 < h <= MAX_DROP_HEIGHT:
        raise ParameterError(f"drop height must be above 0 and at most {MAX_DROP_HEIGHT:g} m, got {h:g}")
    for name, a in zip(("roll", "pitch", "yaw"), angles, strict=True):
        if abs(a) > 360:
            raise ParameterError(f"drop {name} must be within ±360 degrees, got {a:g}")
    if not sim:
        raise ParameterError("a drop places the simulated robot in the air: it needs sim=True (--sim)")
    if fixed_base:
        raise ParameterError("a drop needs the floating base: it cannot be combined with a fixed base (--fixed-base)")
    return values


def check_floating_base(robot: RobotSpec | str) -> None:
    """ParameterError unless the robot's MuJoCo model has a floating base (a drop needs one)."""
    import mujoco

    from felis.sim.robot import load_model, model_path

    spec = robot if isinstance(robot, RobotSpec) else load_spec(robot)
    if not (load_model(model_path(spec)).jnt_type == mujoco.mjtJoint.mjJNT_FREE).any():
        raise ParameterError(f"{spec.name} is fixed to the world: only a free-floating robot can be dropped")


class _SimBackend:
    """Servo-in-the-loop: the servos' horns are the MuJoCo model's joints (module doc)."""

    MAX_STEPS = 20
    ACCEL_RANGE_G = 8.0  # the IMU's accelerometer saturates here (per axis)

    def __init__(self, bus: VirtualBus, spec: RobotSpec, servos: list[VirtualServo], *,
                 servo_params: Mapping[str, object] | None = None, fixed_base: bool = False,
                 imu_mount: SensorMount | None = None, drop: Sequence[float] | None = None):
        import numpy as np

        from felis.drivers.imu import SensorMount, quat_conj, quat_rotate
        from felis.hal import Command
        from felis.sim.robot import MujocoRobot

        self._np, self._Command = np, Command
        self.bus, self.spec, self.servos = bus, spec, servos
        self.robot = MujocoRobot(spec, servo=dict(servo_params or {}), fixed_base=fixed_base)
        self.robot.connect()
        self.robot.arm()
        self.drop_info = None
        if drop is not None:  # held in the air, turned, until torque first comes on (module doc)
            from felis.sim.scenarios import drop as place

            self.drop_info = place(self.robot, *drop)
        self.dt = float(self.robot.model.opt.timestep)
        self.mounts = [s.mount for s in servos]
        self._revisions: tuple[int, ...] = ()
        self.imu: tuple | None = None
        self.imu_mount = imu_mount or SensorMount()
        self._held = True  # physics waits until torque first comes on (`_run`)
        self._reaction = -np.asarray(self.robot.model.opt.gravity, dtype=float)  # specific force at rest, world
        self._quat_conj, self._quat_rotate = quat_conj, quat_rotate
        self._site = None  # the IMU site (mean specific force per sample, module doc)
        if spec.sensors.imu is not None:
            import mujoco

            self._mj = mujoco
            self._site = mujoco.mj_name2id(self.robot.model, mujoco.mjtObj.mjOBJ_SITE, spec.sensors.imu)
            self._vel = np.zeros(6)
        self._site_tv: tuple[float, np.ndarray] | None = None  # (sim time, site world velocity) now
        self._sample_tv: tuple[float, np.ndarray] | None = None  # the same at the previous IMU sample
        self._stop = threading.Event()
        for s in servos:
            s.external = True
        self._publish(self.robot.read())
        for s in servos:  # boot: Goal Position = Present Position (the model's initial pose)
            s.set("goal_position", s.get("present_position"))
        self._sync_command()
        self._emulator = None
        if spec.sensors.imu is not None:
            from felis.drivers.imu import RvcEmulator

            self._emulator = RvcEmulator(self._imu_sample)
            bus.imu_port = self._emulator.port
        self._thread = threading.Thread(target=self._run_guarded, name="virtual-bus sim", daemon=True)

    def start(self) -> None:
        if self._emulator is not None:
            self._emulator.start()
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and the IMU, close the model (idempotent; also when never started)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        if self._emulator is not None:
            self._emulator.stop()
        with contextlib.suppress(Exception):
            self.robot.close()

    def _imu_sample(self):
        """The IMU site's (quat, accel) as the sensor reports it: held still, mounted, drifting (module doc)."""
        with self.bus.lock:
            quat, accel = self.imu
            held = self._held
            now, before = self._site_tv, self._sample_tv
            self._sample_tv = now
        if held:  # still in the operator's hands: the accelerometer reads the reaction to gravity
            accel = self._quat_rotate(self._quat_conj(quat), self._reaction)
        elif now is not None and before is not None and now[0] > before[0]:  # mean over the sample period
            mean = (now[1] - before[1]) / (now[0] - before[0]) + self._reaction
            accel = self._quat_rotate(self._quat_conj(quat), mean)
        quat, accel = self.imu_mount.sample(quat, accel)
        limit = self.ACCEL_RANGE_G * 9.80665
        return quat, self._np.clip(accel, -limit, limit)

    def pose(self, q) -> None:
        """The operator's hands on the simulated robot: joints to ``q`` (rad/m, description order), at rest.

        For calibration by hand while torque is off: physics has not started (it waits for the first
        torque enable) or the joints are unpowered. The servos then read the new angles.
        """
        from felis.sim.scenarios import set_pose

        with self.bus.lock:
            set_pose(self.robot, q)
            self._publish(self.robot.read())

    def _sync_command(self) -> None:
        """Servo memory → Command, when any servo changed (called with the bus lock held)."""
        revisions = tuple(s.revision for s in self.servos)
        if revisions == self._revisions:
            return
        self._revisions = revisions
        np = self._np
        q = np.array([m.joint(s.goal_angle()) for s, m in zip(self.servos, self.mounts, strict=True)])
        torque = np.array([s.torque_enabled for s in self.servos], dtype=bool)
        speed = np.array([abs(s.profile_speed() * m.m_per_rad) for s, m in zip(self.servos, self.mounts,
                                                                                 strict=True)])
        dq_max = None if not speed.any() else np.where(speed > 0, speed, np.inf)
        self.robot.write(self._Command(q=q, dq_max=dq_max, torque=torque))

    def _publish(self, state) -> None:
        """Sim state → servo present items (bus lock held)."""
        effort = state.effort
        for i, (s, m) in enumerate(zip(self.servos, self.mounts, strict=True)):
            theta = m.horn(float(state.q[i]))
            omega = m.direction * float(state.dq[i]) / m.m_per_rad
            tau = m.direction * float(effort[i]) * m.m_per_rad if effort is not None else 0.0
            s.set_present(theta, omega, tau)
        if state.imu is not None:
            self.imu = (state.imu.quat.copy(), state.imu.accel.copy())
            if self._site is not None:
                self._mj.mj_objectVelocity(self.robot.model, self.robot.data, self._mj.mjtObj.mjOBJ_SITE,
                                           self._site, self._vel, 0)  # [angular; linear], world axes
                self._site_tv = (state.t, self._vel[3:].copy())

    def _run_guarded(self) -> None:
        try:
            self._run()
        except Exception as e:  # noqa: BLE001 - report; the servos keep their last state
            print(f"virtual bus: simulation stopped: {type(e).__name__}: {e}", file=sys.stderr)

    def _run(self) -> None:
        dt, lock, robot = self.dt, self.bus.lock, self.robot
        # The operator holds the robot in its start pose until torque first comes on: physics waits, so
        # a run through the bus starts from the same state as the same run on MuJoCo directly.
        while not self._stop.is_set():
            with lock:
                if any(s.torque_enabled for s in self.servos):
                    self._held = False
                    break
            self._stop.wait(dt)
        t0 = time.perf_counter()
        sim_t = 0.0
        while not self._stop.is_set():
            behind = time.perf_counter() - t0 - sim_t
            if behind < dt:
                self._stop.wait(dt - behind)
                continue
            n = int(behind / dt)
            if n > self.MAX_STEPS:
                self.bus.stats.sim_lag_s += (n - self.MAX_STEPS) * dt
                t0 += (n - self.MAX_STEPS) * dt
                n = self.MAX_STEPS
            with lock:
                self.bus.housekeeping()
                self._sync_command()
            robot.advance(n * dt)
            sim_t += n * dt
            state = robot.read()
            with lock:
                self._publish(state)


# ----------------------------------------------------------------------------------------- child process
def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the parent dies, even by SIGKILL (Linux ``PR_SET_PDEATHSIG``),
    so a killed `felis run --port virtual` leaves no virtual bus behind. Elsewhere a no-op."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


class VirtualBusProcess:
    """A virtual bus in a child process (``felis virtual-bus``); see `spawn`."""

    def __init__(self, args: list[str], timeout: float = 20.0):
        env = dict(os.environ)
        env.setdefault("MUJOCO_GL", "egl")
        self.proc = subprocess.Popen([sys.executable, "-m", "felis", "virtual-bus", *args], stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                     preexec_fn=_die_with_parent)
        self._stderr: collections.deque[str] = collections.deque(maxlen=200)
        self._lines: collections.deque[str] = collections.deque()
        self._got_line = threading.Condition()
        self._eof = False
        self._readers = [threading.Thread(target=self._drain_stdout, daemon=True),
                         threading.Thread(target=self._drain_stderr, daemon=True)]
        for t in self._readers:
            t.start()
        self.port = ""
        self.imu_port: str | None = None
        self.summary = ""
        try:
            self._handshake(timeout)
        except BaseException:
            self._kill()
            raise

    def _drain_stdout(self) -> None:
        for line in self.proc.stdout:
            with self._got_line:
                self._lines.append(line.rstrip("\n"))
                self._got_line.notify_all()
        with self._got_line:
            self._eof = True
            self._got_line.notify_all()

    def _drain_stderr(self) -> None:
        for line in self.proc.stderr:
            self._stderr.append(line.rstrip("\n"))

    def _next_line(self, deadline: float) -> str | None:
        with self._got_line:
            while not self._lines and not self._eof:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._got_line.wait(left)
            return self._lines.popleft() if self._lines else None

    def _handshake(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            line = self._next_line(deadline)
            if line is None:
                self._fail("exited" if self._eof else f"printed no port within {timeout:g} s")
            if line.startswith("port: "):
                self.port = line[6:].strip()
            elif line.startswith("imu: "):
                self.imu_port = line[5:].strip()
            elif self.port:
                self.summary = line
                return

    def _fail(self, what: str) -> None:
        self._kill()
        for t in self._readers:
            t.join(timeout=1.0)
        tail = " | ".join(list(self._stderr)[-5:]) or "(no stderr)"
        raise CommError(f"virtual bus process {what} (exit code {self.proc.returncode}); stderr: {tail}")

    def _kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()

    @property
    def stderr(self) -> str:
        """What the child wrote to stderr so far (its statistics after `stop`)."""
        return "\n".join(self._stderr)

    def stop(self) -> int:
        """SIGTERM, wait up to 5 s, then SIGKILL; returns the exit code (idempotent)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._kill()
        for t in self._readers:
            t.join(timeout=2.0)
        return self.proc.returncode

    def __enter__(self) -> VirtualBusProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def spawn(robot: str, *, sim: bool = False, baud: int = 1_000_000, wire_time: bool = False,
          faults: str | None = None, seed: int = 0, timeout: float = 20.0,
          servo_params: str | os.PathLike | None = None, fixed_base: bool = False,
          imu_mount: Sequence[float] | None = None, imu_drift: Sequence[float] | None = None,
          drop: Sequence[float] | None = None) -> VirtualBusProcess:
    """Run ``felis virtual-bus`` for ``robot`` in a child process; raises CommError if it does not come up.

    ``servo_params`` (a servo parameter file, `felis.sim.servo_file`) and ``fixed_base`` apply to the
    simulation (``sim=True``); so do ``imu_mount`` (unit quaternion w, x, y, z, passed on as
    ``--imu-mount-deg`` roll, pitch, yaw), ``imu_drift`` (rad/s) and ``drop`` (height m, roll°, pitch°,
    yaw°: held in the air until torque first comes on; checked here by `check_drop`), as in
    `VirtualBus.for_robot`.
    """
    args = ["--robot", str(robot), "--baud", str(baud), "--seed", str(seed)]
    if sim:
        args.append("--sim")
    drop = check_drop(drop, sim=sim, fixed_base=fixed_base)  # one line here, not a failed child
    if drop is not None:
        check_floating_base(robot)
        args.append("--drop=" + ",".join(repr(v) for v in drop))
    if servo_params is not None:
        args += ["--servo-params", os.fspath(servo_params)]
    if fixed_base:
        args.append("--fixed-base")
    if imu_mount is not None or imu_drift is not None:
        from felis.drivers.imu import SensorMount

        try:  # fail here, with its message, rather than in the child
            SensorMount(imu_mount, imu_drift)
        except ValueError as e:
            raise ParameterError(str(e)) from None
    if imu_mount is not None:
        from felis.drivers.imu import rvc_from_quat

        yaw, pitch, roll = rvc_from_quat(imu_mount)
        args.append("--imu-mount-deg=" + ",".join(f"{math.degrees(a):.12g}" for a in (roll, pitch, yaw)))
    if imu_drift is not None:
        args.append("--imu-drift=" + ",".join(repr(float(v)) for v in imu_drift))
    if wire_time:
        args.append("--wire-time")
    if faults:
        parse_faults(faults)  # fail here, with the parser's message, rather than in the child
        args += ["--faults", faults]
    return VirtualBusProcess(args, timeout=timeout)
