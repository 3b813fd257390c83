"""One emulated X-series servo (`VirtualServo`): control-table memory, the rules of every instruction, the
Bus Watchdog, hardware errors, and either standalone dynamics or a horn driven from outside (`Mount` maps
the horn to its joint). ``handle(packet)`` runs packets against this servo alone;
`felis.drivers.virtual.dispatch` runs them against many.

The servo model is documented next to its code: the instruction and status rules (status levels, status
errors, hardware errors and their shutdown latch, REBOOT, FACTORY_RESET, CLEAR, REG_WRITE/ACTION) in
`felis.drivers.virtual.instructions`, the position frame and the standalone dynamics in
`felis.drivers.virtual.horn`. This module holds the servo itself: its control-table memory (boot, Indirect
Address mapping, ``get``/``set``), hardware errors, and what a write changes besides memory.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import BAUD_RATES, control_table
from felis.drivers.virtual.horn import CENTRE, I32, U16, HornModel, Mount, _Standalone
from felis.drivers.virtual.instructions import Instructions
from felis.drivers.virtual.memory import (
    BAUD,
    BUS_WATCHDOG,
    DRIVE_MODE,
    FIRMWARE,
    GOAL_POSITION,
    HARDWARE_ERROR,
    HOMING_OFFSET,
    ID,
    MOVING_THRESHOLD,
    POSITION_P,
    PRESENT_POSITION,
    PRESENT_TEMPERATURE,
    PRESENT_VOLTAGE,
    RETURN_DELAY,
    SHUTDOWN,
    STATUS_RETURN_LEVEL,
    TORQUE_ENABLE,
    hardware_bits,
)
from felis.errors import ParameterError
from felis.servos import emulated

TEMPERATURE_C = 32
_CACHED = frozenset((DRIVE_MODE, HOMING_OFFSET, MOVING_THRESHOLD, POSITION_P))  # see VirtualServo._cache_settings


class VirtualServo(Instructions, HornModel):
    """One emulated X-series servo: control-table memory, instruction rules and dynamics (module doc).

    Args:
        model: model name (``"XL330-M288-T"``) or Model Number (``1190``): any model
            `felis.drivers.dynamixel.controltable.CONTROL_TABLES` holds; another is a one-line ParameterError.
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
        self.datasheet = emulated(self.model)  # datasheet figures, or a flagged stand-in's (felis.servos)
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
        amps = self.datasheet.stall_current
        self._kt = self.datasheet.stall_torque / amps if amps and unit is not None else None
        self._current_unit = unit.scale if unit is not None else None
        self.mem = bytearray()
        self._boot(self.table.defaults(), id, baud_code)
        self._standalone = _Standalone(self.datasheet, self._t)  # made now: not on the first reply after torque on

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
        U16.pack_into(mem, PRESENT_VOLTAGE, round(self.datasheet.voltage * 10))
        self.mem = mem
        self.id = dxl_id
        self.baud_bps = BAUD_RATES[baud_code]
        self._registered = None
        self._latched = False
        self._omega = self._torque = 0.0
        if not self.external:  # the absolute encoder knows one turn: extended position's turn count starts again
            self._theta = math.remainder(self._theta, 2.0 * math.pi)
        self._cache_settings()
        self._map_indirect()
        self._last_rx = self.clock()
        self._refresh()
        I32.pack_into(mem, GOAL_POSITION, I32.unpack_from(mem, PRESENT_POSITION)[0])
        self.revision += 1

    def _map_indirect(self) -> None:
        """The address each Indirect Data byte stands for, from the Indirect Address items."""
        if self.indirect is not None:
            a0, d0, n = self.indirect
            self._targets = [U16.unpack_from(self.mem, a0 + 2 * k)[0] for k in range(n)]
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


    # -------------------------------------------------------------- writes
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


__all__ = ["CENTRE", "Mount", "VirtualServo"]
