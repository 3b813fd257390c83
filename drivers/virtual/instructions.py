"""The instructions of an emulated servo (`Instructions`, inherited by `VirtualServo`): who answers, PING,
READ (with Indirect Data), WRITE and its checks, REG_WRITE/ACTION, REBOOT, FACTORY_RESET and CLEAR.

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
it (and answers the write's error if, in between, it became invalid). ▸ Profile
Acceleration, time-based profiles (Drive Mode bit 2), PWM and current control modes are not
modelled: in modes 0 and 16 the horn holds still.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import EEPROM_END, ControlTable
from felis.drivers.virtual.dispatch import dispatch
from felis.drivers.virtual.horn import I32, U16
from felis.drivers.virtual.memory import (
    BAUD,
    BUS_WATCHDOG,
    CURRENT_LIMIT,
    DYNAMIC_START,
    GOAL_CURRENT,
    GOAL_POSITION,
    GOAL_VELOCITY,
    GOALS,
    ID,
    MAX_POSITION,
    MIN_POSITION,
    OPERATING_MODE,
    REGISTERED,
    STATUS_RETURN_LEVEL,
    TORQUE_ENABLE,
    VELOCITY_LIMIT,
    WATCHDOG_ERROR,
    write_plan,
)
from felis.drivers.virtual.packets import READS, status_packet

CLEAR_MULTI_TURN = b"\x01\x44\x58\x4c\x22"


class Instructions:
    """The instruction rules of `VirtualServo` (module doc); the servo provides its memory, boot and horn."""

    table: ControlTable
    mem: bytearray
    id: int
    firmware: int
    indirect: tuple[int, int, int] | None
    _registered: tuple[int, bytes] | None
    _latched: bool
    _targets: list[int]
    _runs: list[tuple[int, int, int]]
    _gathers: dict[tuple[int, int], list[tuple[int, int]]]

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
            goal = I32.unpack_from(cand, GOAL_POSITION)[0]
            lo, hi = I32.unpack_from(cand, MIN_POSITION)[0], I32.unpack_from(cand, MAX_POSITION)[0]
            if not lo <= goal <= hi:
                return P.DATA_LIMIT_ERROR
        if GOAL_VELOCITY in addrs and abs(I32.unpack_from(cand, GOAL_VELOCITY)[0]) > I32.unpack_from(
                cand, VELOCITY_LIMIT)[0]:
            return P.DATA_LIMIT_ERROR
        if GOAL_CURRENT in addrs and self.table.at(CURRENT_LIMIT) is not None and abs(
                struct.unpack_from("<h", cand, GOAL_CURRENT)[0]) > U16.unpack_from(cand, CURRENT_LIMIT)[0]:
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


_HANDLERS: dict[int, Callable[[Instructions, bytes], tuple[int, bytes]]] = {
    P.PING: Instructions._ping, P.READ: Instructions._read, P.WRITE: Instructions._write_inst,
    P.REG_WRITE: Instructions._reg_write, P.ACTION: Instructions._action, P.REBOOT: Instructions._reboot,
    P.FACTORY_RESET: Instructions._factory_reset, P.CLEAR: Instructions._clear,
}
