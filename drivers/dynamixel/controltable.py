"""Dynamixel X-series control tables as data: one source for the bus driver and the virtual bus.

An :class:`Item` is one control-table entry: address, size in bytes, access (``R``/``RW``), memory
area (EEPROM below address 64, RAM from 64), factory default, valid raw range, and the conversion
to SI units::

    si = (raw - offset) * scale          raw = round(si / scale + offset)

with ``offset = 2048`` for absolute positions (the centre tick is the joint zero, see
``felis.servos``) and 0 otherwise. Items without a physical unit (gains, modes, flags) have
``unit = ""`` and ``scale = 1``. Signed items are two's complement, little-endian.

Names are snake_case (``present_position``); :meth:`ControlTable.item` also accepts the e-Manual
spelling (``"Present Position"``) and suggests the nearest name on a typo.

Per-model differences (``shared/reference/dynamixel.md``): XL330-M288-T has Current Limit and Goal
Current in 1 mA units and no 4.5 Mbps; XL430-W250-T has no current items, its address 126 is
Present Load (0.1 %), and no current-based operating modes; XM430-W350-T has current in 2.69 mA
units. Defaults and ranges follow the ROBOTIS e-Manual; the few we could not check are marked.

Indirect Addressing (`ControlTable.indirect` = Indirect Address 1's address, Indirect Data 1's address,
count): ``indirect_address_n`` (2 bytes, RAM) holds the address that ``indirect_data_n`` (1 byte)
stands for; a read or write of the data byte acts on that address, with its access and range, so
scattered items can be gathered into one block for one sync read. Valid targets are the RAM area,
64…661 (e-Manual); the factory value of entry n is 224 + n − 1 (the data byte itself). The first bank
only: XL330-M288-T has entries 1–20 (address 168…206, data 224…243), XL430-W250-T and XM430-W350-T
1–28 (168…222, data 224…251; their second bank at 578/634 is not modelled). Addresses and counts are
those of the SDK's shipped tables (``dynamixel_easy_sdk/control_table/*.model``: ``Indirect Address 1``
168, ``Indirect Data 1`` 224; the XL330's read block starts at entry 7, 180/230) and the e-Manual.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field

from felis.errors import ParameterError
from felis.servos import HARDWARE_ERROR_BITS, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, SERVOS, hardware_error_names

EEPROM_END = 64  # addresses below are EEPROM: writable only while Torque Enable is 0
CENTRE_TICK = 2048

# Baud Rate item (addr 8): code -> bits per second
BAUD_RATES: dict[int, int] = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000,
                              6: 4_000_000, 7: 4_500_000}
OPERATING_MODES: dict[int, str] = {0: "current", 1: "velocity", 3: "position", 4: "extended_position",
                                   5: "current_based_position", 16: "pwm"}
HARDWARE_ERRORS = HARDWARE_ERROR_BITS  # Hardware Error Status (addr 70) / Shutdown (addr 63) bit -> name
# Fast Sync Read needs firmware >= 45 on X-series (ROBOTIS release notes; assumption, not in reference).
FAST_SYNC_READ_MIN_FIRMWARE = 45

_PROFILE_ACC_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0  # 214.577 rev/min² per unit


@dataclass(frozen=True)
class Item:
    """One control-table entry. ``lo``/``hi`` bound the raw value a WRITE may carry."""

    name: str
    addr: int
    size: int
    access: str  # "R" or "RW"
    default: int
    lo: int
    hi: int
    unit: str = ""
    scale: float = 1.0
    offset: int = 0
    signed: bool = False
    values: dict[int, object] | None = None  # enumerated codes (baud rate, operating mode)

    @property
    def area(self) -> str:
        return "EEPROM" if self.addr < EEPROM_END else "RAM"

    @property
    def writable(self) -> bool:
        return self.access == "RW"

    def to_si(self, raw: int) -> float:
        """Raw control-table value -> SI (rad, rad/s, A, V, s, °C, fraction); enum codes map to
        their value (baud rate in bps, mode name)."""
        if self.values is not None and raw in self.values:
            return self.values[raw]  # type: ignore[return-value]
        return (raw - self.offset) * self.scale

    def from_si(self, value: float) -> int:
        """SI -> raw, checked against the item's range. Enumerated items take the value (e.g. 1000000
        for a baud rate) or the mode name."""
        if self.values is not None:
            for code, v in self.values.items():
                if v == value:
                    return code
            known = ", ".join(str(v) for v in self.values.values())
            raise ParameterError(f"{self.name}: {value!r} is not one of {known}")
        if not math.isfinite(value):
            raise ParameterError(f"{self.name}: value must be finite, got {value}")
        scaled = value / self.scale + self.offset
        if not math.isfinite(scaled) or abs(scaled) > 2**40:  # e.g. 1e308 rad: far outside any item
            raise ParameterError(f"{self.name}: {value:g} {self.unit} is out of range ({self.describe_range()})")
        raw = round(scaled)
        self.check(raw)
        return raw

    def check(self, raw: int) -> None:
        if not self.lo <= raw <= self.hi:
            raise ParameterError(f"{self.name}: raw value {raw} is outside {self.lo}…{self.hi}"
                                 + (f" ({self.describe_range()})" if self.unit else ""))

    def describe_range(self) -> str:
        return f"{self.to_si(self.lo):.4g}…{self.to_si(self.hi):.4g} {self.unit}"

    def encode(self, raw: int) -> bytes:
        return int(raw).to_bytes(self.size, "little", signed=self.signed)

    def decode(self, data: bytes | bytearray) -> int:
        return int.from_bytes(data[: self.size], "little", signed=self.signed)


@dataclass(frozen=True)
class ControlTable:
    """The control table of one servo model: items by name and by address."""

    model: str
    model_number: int
    items: dict[str, Item]
    baud_rates: dict[int, int]
    operating_modes: dict[int, str]
    indirect: tuple[int, int, int] | None = None  # (Indirect Address 1, Indirect Data 1, count) (module doc)
    _by_addr: dict[int, Item] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self._by_addr.update({it.addr: it for it in self.items.values()})

    def item(self, name: str) -> Item:
        """Look up an item by snake_case or e-Manual name; unknown names raise ParameterError."""
        key = normalize_name(name)
        try:
            return self.items[key]
        except KeyError:
            near = difflib.get_close_matches(key, self.items, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else f"; known: {', '.join(self.items)}"
            raise ParameterError(f"{self.model} has no control-table item {name!r}{hint}") from None

    def at(self, addr: int) -> Item | None:
        """The item starting at ``addr``, if any."""
        return self._by_addr.get(addr)

    def covering(self, addr: int, length: int) -> list[Item]:
        """Items overlapping the byte range [addr, addr+length)."""
        end = addr + length
        return [it for it in self.items.values() if it.addr < end and addr < it.addr + it.size]

    @property
    def size(self) -> int:
        """Bytes of memory the table spans (one past the last item)."""
        return max(it.addr + it.size for it in self.items.values())

    def defaults(self) -> bytearray:
        """Factory memory image."""
        mem = bytearray(self.size)
        for it in self.items.values():
            mem[it.addr: it.addr + it.size] = it.encode(it.default)
        return mem


def normalize_name(name: str) -> str:
    """``"Present Position"`` / ``"present-position"`` -> ``"present_position"``."""
    return re.sub(r"[\s\-]+", "_", name.strip()).lower()


INDIRECT_ADDRESS, INDIRECT_DATA = 168, 224  # Indirect Address 1 / Indirect Data 1 on every X-series model here
INDIRECT_TARGETS = (EEPROM_END, 661)  # what an Indirect Address may point at: the RAM area


def _table(model: str, *, firmware: int, current_unit_ma: float | None, baud_codes: range, modes: tuple[int, ...],
           voltage: tuple[int, int, int, int], temperature_limit: int, velocity_limit: tuple[int, int],
           current_limit: int | None, gains: tuple[int, int, int], velocity_gains: tuple[int, int],
           indirect: int = 0) -> ControlTable:
    s = SERVOS[model]
    vmax_default, vmax_hi = velocity_limit
    max_v, min_v, v_lo, v_hi = voltage
    d, i, p = gains
    vi, vp = velocity_gains
    rpm = RAD_S_PER_VELOCITY_UNIT
    tick = RAD_PER_TICK
    bauds = {c: BAUD_RATES[c] for c in baud_codes}
    mode_names = {m: OPERATING_MODES[m] for m in modes}
    items = [
        Item("model_number", 0, 2, "R", s.model_number, 0, 65535),
        Item("model_information", 2, 4, "R", 0, 0, 2**32 - 1),
        Item("firmware_version", 6, 1, "R", firmware, 0, 255),
        Item("id", 7, 1, "RW", 1, 0, 252),
        Item("baud_rate", 8, 1, "RW", 1, min(bauds), max(bauds), "bps", values=dict(bauds)),
        Item("return_delay_time", 9, 1, "RW", 250, 0, 254, "s", 2e-6),
        Item("drive_mode", 10, 1, "RW", 0, 0, 13),
        Item("operating_mode", 11, 1, "RW", 3, 0, 16, values=dict(mode_names)),
        Item("secondary_id", 12, 1, "RW", 255, 0, 255),
        Item("protocol_type", 13, 1, "RW", 2, 1, 2),
        Item("homing_offset", 20, 4, "RW", 0, -1_044_479, 1_044_479, "rad", tick, signed=True),
        Item("moving_threshold", 24, 4, "RW", 10, 0, 1023, "rad/s", rpm),
        Item("temperature_limit", 31, 1, "RW", temperature_limit, 0, 100, "°C"),
        Item("max_voltage_limit", 32, 2, "RW", max_v, v_lo, v_hi, "V", 0.1),
        Item("min_voltage_limit", 34, 2, "RW", min_v, v_lo, v_hi, "V", 0.1),
        Item("pwm_limit", 36, 2, "RW", 885, 0, 885, "", 1 / 885),
    ]
    if current_limit is not None:
        items.append(Item("current_limit", 38, 2, "RW", current_limit, 0, current_limit, "A",
                          current_unit_ma / 1000))
    items += [
        Item("velocity_limit", 44, 4, "RW", vmax_default, 0, vmax_hi, "rad/s", rpm),
        Item("max_position_limit", 48, 4, "RW", 4095, 0, 4095, "rad", tick, CENTRE_TICK),
        Item("min_position_limit", 52, 4, "RW", 0, 0, 4095, "rad", tick, CENTRE_TICK),
        Item("shutdown", 63, 1, "RW", 52, 0, 255),
        Item("torque_enable", 64, 1, "RW", 0, 0, 1),
        Item("led", 65, 1, "RW", 0, 0, 1),
        Item("status_return_level", 68, 1, "RW", 2, 0, 2),
        Item("registered_instruction", 69, 1, "R", 0, 0, 1),
        Item("hardware_error_status", 70, 1, "R", 0, 0, 255),
        Item("velocity_i_gain", 76, 2, "RW", vi, 0, 16383),
        Item("velocity_p_gain", 78, 2, "RW", vp, 0, 16383),
        Item("position_d_gain", 80, 2, "RW", d, 0, 16383),
        Item("position_i_gain", 82, 2, "RW", i, 0, 16383),
        Item("position_p_gain", 84, 2, "RW", p, 0, 16383),
        Item("feedforward_2nd_gain", 88, 2, "RW", 0, 0, 16383),
        Item("feedforward_1st_gain", 90, 2, "RW", 0, 0, 16383),
        Item("bus_watchdog", 98, 1, "RW", 0, 0, 127, "s", 0.02),
        Item("goal_pwm", 100, 2, "RW", 0, -885, 885, "", 1 / 885, signed=True),
    ]
    if current_limit is not None:
        items.append(Item("goal_current", 102, 2, "RW", 0, -current_limit, current_limit, "A",
                          current_unit_ma / 1000, signed=True))
    items += [
        Item("goal_velocity", 104, 4, "RW", 0, -vmax_hi, vmax_hi, "rad/s", rpm, signed=True),
        Item("profile_acceleration", 108, 4, "RW", 0, 0, 32767, "rad/s²", _PROFILE_ACC_RAD_S2),
        Item("profile_velocity", 112, 4, "RW", 0, 0, 32767, "rad/s", rpm),
        Item("goal_position", 116, 4, "RW", 0, -1_048_575, 1_048_575, "rad", tick, CENTRE_TICK, signed=True),
        Item("realtime_tick", 120, 2, "R", 0, 0, 32767, "s", 1e-3),
        Item("moving", 122, 1, "R", 0, 0, 1),
        Item("moving_status", 123, 1, "R", 0, 0, 255),
        Item("present_pwm", 124, 2, "R", 0, -885, 885, "", 1 / 885, signed=True),
    ]
    if current_unit_ma is not None:
        items.append(Item("present_current", 126, 2, "R", 0, -32768, 32767, "A", current_unit_ma / 1000, signed=True))
    else:
        items.append(Item("present_load", 126, 2, "R", 0, -1000, 1000, "", 0.001, signed=True))
    items += [
        Item("present_velocity", 128, 4, "R", 0, -2**31, 2**31 - 1, "rad/s", rpm, signed=True),
        Item("present_position", 132, 4, "R", CENTRE_TICK, -2**31, 2**31 - 1, "rad", tick, CENTRE_TICK,
             signed=True),
        Item("velocity_trajectory", 136, 4, "R", 0, -2**31, 2**31 - 1, "rad/s", rpm, signed=True),
        Item("position_trajectory", 140, 4, "R", 0, -2**31, 2**31 - 1, "rad", tick, CENTRE_TICK, signed=True),
        Item("present_input_voltage", 144, 2, "R", (max_v + min_v) // 2, 0, 65535, "V", 0.1),
        Item("present_temperature", 146, 1, "R", 30, 0, 255, "°C"),
    ]
    lo, hi = INDIRECT_TARGETS
    items += [Item(f"indirect_address_{n}", INDIRECT_ADDRESS + 2 * (n - 1), 2, "RW", INDIRECT_DATA + n - 1, lo, hi)
              for n in range(1, indirect + 1)]
    items += [Item(f"indirect_data_{n}", INDIRECT_DATA + n - 1, 1, "RW", 0, 0, 255) for n in range(1, indirect + 1)]
    return ControlTable(model, s.model_number, {it.name: it for it in items}, bauds, mode_names,
                        indirect=(INDIRECT_ADDRESS, INDIRECT_DATA, indirect) if indirect else None)


CONTROL_TABLES: dict[str, ControlTable] = {
    "XL330-M288-T": _table("XL330-M288-T", firmware=52, current_unit_ma=1.0, baud_codes=range(0, 7),
                           modes=(0, 1, 3, 4, 5, 16), voltage=(70, 35, 31, 70), temperature_limit=70,
                           velocity_limit=(445, 2047), current_limit=1750, gains=(0, 0, 400),
                           velocity_gains=(1000, 180), indirect=20),
    "XL430-W250-T": _table("XL430-W250-T", firmware=46, current_unit_ma=None, baud_codes=range(0, 8),
                           modes=(1, 3, 4, 16), voltage=(140, 60, 60, 140), temperature_limit=72,
                           velocity_limit=(265, 1023), current_limit=None, gains=(4000, 0, 640),
                           velocity_gains=(1000, 100), indirect=28),
    "XM430-W350-T": _table("XM430-W350-T", firmware=46, current_unit_ma=2.69, baud_codes=range(0, 8),
                           modes=(0, 1, 3, 4, 5, 16), voltage=(160, 95, 95, 160), temperature_limit=80,
                           velocity_limit=(200, 1023), current_limit=1193, gains=(0, 0, 800),
                           velocity_gains=(1920, 100), indirect=28),
}
_BY_NUMBER = {t.model_number: t for t in CONTROL_TABLES.values()}



def shared_item(*names: str) -> Item:
    """The item that every model here has at one address and size, under one of ``names`` (alternatives: the
    XL430 has Present Load where the others have Present Current). Code that addresses servos without
    knowing their model (group reads and writes, the emulator's hot path) takes addresses from here, by
    name, rather than as numbers. ParameterError if no model has it or the models disagree."""
    found = [t.items[n] for t in CONTROL_TABLES.values() for n in names if n in t.items]
    if not found or len({(it.addr, it.size) for it in found}) != 1:
        raise ParameterError(f"control-table item {' / '.join(names)} is not at one address in every model")
    return found[0]


def address(*names: str) -> int:
    """Address of a `shared_item`."""
    return shared_item(*names).addr


def span(first: str | tuple[str, ...], last: str | tuple[str, ...]) -> tuple[int, int]:
    """(address, length) of the contiguous block from item ``first`` through item ``last`` (`shared_item`
    names; a tuple lists alternatives)."""
    a = shared_item(*((first,) if isinstance(first, str) else first))
    b = shared_item(*((last,) if isinstance(last, str) else last))
    return a.addr, b.addr + b.size - a.addr


# The block one sync read fetches each tick: present current/load, velocity, position.
STATE_BLOCK = span(("present_current", "present_load"), "present_position")


def control_table(model: str | int) -> ControlTable:
    """The table for a model name (``"XL330-M288-T"``) or Model Number (``1200``)."""
    table = _BY_NUMBER.get(model) if isinstance(model, int) else CONTROL_TABLES.get(model)
    if table is None:
        known = ", ".join(f"{t.model} ({t.model_number})" for t in CONTROL_TABLES.values())
        raise ParameterError(f"unknown Dynamixel model {model!r}; known: {known}")
    return table


def model_name(model_number: int) -> str:
    """Model name for a Model Number, or ``"unknown (N)"``."""
    t = _BY_NUMBER.get(model_number)
    return t.model if t else f"unknown ({model_number})"


decode_hardware_error = hardware_error_names
