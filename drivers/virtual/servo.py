"""One emulated X-series servo (`VirtualServo`): control-table memory, the rules of every instruction, the
Bus Watchdog, hardware errors, and either standalone dynamics or a horn driven from outside (`Mount` maps
the horn to its joint). ``handle(packet)`` runs packets against this servo alone;
`felis.drivers.virtual.dispatch` runs them against many.

Servo model (choices the reference, ``shared/reference/dynamixel.md``, leaves open are marked ▸)
-----------------------------------------------------------------------------------------------
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
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import BAUD_RATES, CENTRE_TICK, EEPROM_END, control_table
from felis.drivers.virtual.dispatch import dispatch
from felis.drivers.virtual.memory import (
    BAUD,
    BUS_WATCHDOG,
    CURRENT_LIMIT,
    DRIVE_MODE,
    DYNAMIC_START,
    FIRMWARE,
    GOAL_CURRENT,
    GOAL_POSITION,
    GOAL_VELOCITY,
    GOALS,
    HARDWARE_ERROR,
    HOMING_OFFSET,
    ID,
    MAX_POSITION,
    MIN_POSITION,
    MOVING,
    MOVING_THRESHOLD,
    OPERATING_MODE,
    POSITION_MODES,
    POSITION_P,
    PRESENT_CURRENT,
    PRESENT_POSITION,
    PRESENT_TEMPERATURE,
    PRESENT_VOLTAGE,
    PROFILE_VELOCITY,
    REALTIME_TICK,
    REGISTERED,
    RETURN_DELAY,
    SHUTDOWN,
    STATUS_RETURN_LEVEL,
    TORQUE_ENABLE,
    VELOCITY_LIMIT,
    WATCHDOG_ERROR,
    WATCHDOG_UNIT_S,
    hardware_bits,
    write_plan,
)
from felis.drivers.virtual.packets import READS, status_packet
from felis.errors import ParameterError
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, SERVOS, STALL_CURRENT_A, TICKS_PER_REV

TAU_S = 0.05  # first-order time constant of the standalone horn
TEMPERATURE_C = 32
CENTRE = CENTRE_TICK
_CACHED = frozenset((DRIVE_MODE, HOMING_OFFSET, MOVING_THRESHOLD, POSITION_P))  # see VirtualServo._cache_settings
CLEAR_MULTI_TURN = b"\x01\x44\x58\x4c\x22"

_PRESENT = struct.Struct("<hii")  # present current/load, velocity, position (at `PRESENT_CURRENT`)
_I32 = struct.Struct("<i")
_U16 = struct.Struct("<H")


@dataclass(frozen=True)
class Mount:
    """How a servo horn drives its joint: θ = direction·q/m_per_rad + zero + offset (rad)."""

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
        unit = self.table.items.get("present_current")  # None: Present Load (XL430)
        self._kt = (self.datasheet.stall_torque / STALL_CURRENT_A[self.model]
                    if self.model in STALL_CURRENT_A and unit is not None else None)
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
        mem[FIRMWARE] = self.firmware
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
        plan = write_plan(self.table, addr, len(data))
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
            checked.append((write_plan(self.table, a, len(d)), cand))
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

