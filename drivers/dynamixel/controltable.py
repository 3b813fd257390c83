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

Where the tables come from: addresses and sizes are read at import from the tables the installed
``dynamixel-sdk`` ships (``dynamixel_easy_sdk/control_table/*.model``; which models and why, and which files
are skipped: `felis.drivers.dynamixel.models`). Everything else is typed here once, keyed by item name
(`_rules`), with the per-model numbers the rules need (defaults, limits, current unit) from
`models.MODELS` and the factory P/D gains from `felis.servos`. Per-model differences the e-Manual gives:
Current Limit / Goal / Present Current in 1 mA on the X330s, 1.34 mA on XH430-V, 2.69 mA on the other X430/X540;
the XL430, 2XL430, XC430 and 2XC430 have no current items, their address 126 is Present Load (0.1 %), and no
current-based operating modes; the X330s have no 4.5 Mbps and have PWM Slope (62); the XM540/XH540/XD540 have
External Ports (56…58, 152…157); the XW series has no LED. Defaults and ranges follow the ROBOTIS e-Manual.
The SDK aliases ``Indirect Address/Data Write/Read`` are not items.

Indirect Addressing (`ControlTable.indirect` = Indirect Address 1's address, Indirect Data 1's address,
count): ``indirect_address_n`` (2 bytes, RAM) holds the address that ``indirect_data_n`` (1 byte)
stands for; a read or write of the data byte acts on that address, with its access and range, so
scattered items can be gathered into one block for one sync read. Valid targets are the RAM area,
64…661 (e-Manual); the factory value of entry n is Indirect Data 1 + n − 1 (the data byte itself). The first
bank only: the X330s have entries 1–20, the others 1–28 (their second bank at 578/634 is not modelled). The
addresses of entry 1 are the SDK file's (``Indirect Address 1`` 168, ``Indirect Data 1`` 224), the counts
the e-Manual's.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field

from felis.drivers.dynamixel.models import MODELS, ModelSpec, sdk_items, sdk_model_files
from felis.errors import ParameterError
from felis.servos import (
    HARDWARE_ERROR_BITS,
    RAD_PER_TICK,
    RAD_S_PER_VELOCITY_UNIT,
    SERVOS,
    ServoModel,
    canonical_name,
    hardware_error_names,
)

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


INDIRECT_ADDRESS, INDIRECT_DATA = 168, 224  # Indirect Address 1 / Indirect Data 1 as the SDK files give them
INDIRECT_TARGETS = (EEPROM_END, 661)  # what an Indirect Address may point at: the RAM area
_SDK_ALIASES = ("Indirect Address Write", "Indirect Data Write", "Indirect Address Read", "Indirect Data Read")
_SDK_NAMES = {"Secondary(Shadow) ID": "secondary_id"}  # SDK spelling -> felis name, where normalize_name differs


def _rules(m: ModelSpec, s: ServoModel) -> dict[str, tuple]:
    """Item name -> (access, default, lo, hi, unit, scale, offset, signed, values) for one model: the typed layer
    the SDK files lack. Names the model's SDK file lacks are simply not used."""
    vmax_default, vmax_hi = m.velocity_limit
    max_v, min_v, v_lo, v_hi = m.voltage
    _d, i_gain, _p = m.gains
    vi, vp = m.velocity_gains
    rpm, tick = RAD_S_PER_VELOCITY_UNIT, RAD_PER_TICK
    bauds = {c: BAUD_RATES[c] for c in m.baud_codes}
    modes = {k: OPERATING_MODES[k] for k in m.modes}
    amp = None if m.current_unit_ma is None else m.current_unit_ma / 1000
    cl = m.current_limit
    pos = ("rad", tick, CENTRE_TICK, True)
    r: dict[str, tuple] = {
        "model_number": ("R", m.number, 0, 65535),
        "model_information": ("R", 0, 0, 2**32 - 1),
        "firmware_version": ("R", m.firmware, 0, 255),
        "id": ("RW", 1, 0, 252),
        "baud_rate": ("RW", 1, min(bauds), max(bauds), "bps", 1.0, 0, False, bauds),
        "return_delay_time": ("RW", 250, 0, 254, "s", 2e-6),
        "drive_mode": ("RW", 0, 0, 13),
        "operating_mode": ("RW", 3, 0, 16, "", 1.0, 0, False, modes),
        "secondary_id": ("RW", 255, 0, 255),
        "protocol_type": ("RW", 2, 1, 2),
        "homing_offset": ("RW", 0, -1_044_479, 1_044_479, "rad", tick, 0, True),
        "moving_threshold": ("RW", 10, 0, 1023, "rad/s", rpm),
        "temperature_limit": ("RW", m.temperature_limit, 0, 100, "°C"),
        "max_voltage_limit": ("RW", max_v, v_lo, v_hi, "V", 0.1),
        "min_voltage_limit": ("RW", min_v, v_lo, v_hi, "V", 0.1),
        "pwm_limit": ("RW", 885, 0, 885, "", 1 / 885),
        "velocity_limit": ("RW", vmax_default, 0, vmax_hi, "rad/s", rpm),
        "max_position_limit": ("RW", 4095, 0, 4095, "rad", tick, CENTRE_TICK),
        "min_position_limit": ("RW", 0, 0, 4095, "rad", tick, CENTRE_TICK),
        "shutdown": ("RW", 52, 0, 255),
        "torque_enable": ("RW", 0, 0, 1),
        "led": ("RW", 0, 0, 1),
        "status_return_level": ("RW", 2, 0, 2),
        "registered_instruction": ("R", 0, 0, 1),
        "hardware_error_status": ("R", 0, 0, 255),
        "velocity_i_gain": ("RW", vi, 0, 16383),
        "velocity_p_gain": ("RW", vp, 0, 16383),
        "position_d_gain": ("RW", s.position_d_gain, 0, 16383),
        "position_i_gain": ("RW", i_gain, 0, 16383),
        "position_p_gain": ("RW", s.position_p_gain, 0, 16383),
        "feedforward_2nd_gain": ("RW", 0, 0, 16383),
        "feedforward_1st_gain": ("RW", 0, 0, 16383),
        "bus_watchdog": ("RW", 0, 0, 127, "s", 0.02),
        "goal_pwm": ("RW", 0, -885, 885, "", 1 / 885, 0, True),
        "goal_velocity": ("RW", 0, -vmax_hi, vmax_hi, "rad/s", rpm, 0, True),
        "profile_acceleration": ("RW", 0, 0, 32767, "rad/s²", _PROFILE_ACC_RAD_S2),
        "profile_velocity": ("RW", 0, 0, 32767, "rad/s", rpm),
        "goal_position": ("RW", 0, -1_048_575, 1_048_575, *pos),
        "realtime_tick": ("R", 0, 0, 32767, "s", 1e-3),
        "moving": ("R", 0, 0, 1),
        "moving_status": ("R", 0, 0, 255),
        "present_pwm": ("R", 0, -885, 885, "", 1 / 885, 0, True),
        "present_load": ("R", 0, -1000, 1000, "", 0.001, 0, True),
        "present_velocity": ("R", 0, -2**31, 2**31 - 1, "rad/s", rpm, 0, True),
        "present_position": ("R", CENTRE_TICK, -2**31, 2**31 - 1, *pos),
        "velocity_trajectory": ("R", 0, -2**31, 2**31 - 1, "rad/s", rpm, 0, True),
        "position_trajectory": ("R", 0, -2**31, 2**31 - 1, *pos),
        "present_input_voltage": ("R", (max_v + min_v) // 2, 0, 65535, "V", 0.1),
        "present_temperature": ("R", 30, 0, 255, "°C"),
    }
    if amp is not None:
        r["current_limit"] = ("RW", cl, 0, cl, "A", amp)
        r["goal_current"] = ("RW", 0, -cl, cl, "A", amp, 0, True)
        r["present_current"] = ("R", 0, -32768, 32767, "A", amp, 0, True)
    if m.pwm_slope is not None:
        r["pwm_slope"] = ("RW", m.pwm_slope[0], 1, 255, "V/s", m.pwm_slope[1])
    for n in (1, 2, 3):  # XM540/XH540/XD540 (e-Manual: mode 0…3, factory 3; data raw, meaning set by the mode)
        r[f"external_port_mode_{n}"] = ("RW", 3, 0, 3)
        r[f"external_port_data_{n}"] = ("RW", 0, 0, 65535)
    for name, value in m.extra.items():
        r[name] = (r[name][0], value, *r[name][2:])
    return r


def _item(name: str, addr: int, size: int, rule: tuple) -> Item:
    access, default, lo, hi, *rest = rule
    unit, scale, offset, signed, values = (*rest, *("", 1.0, 0, False, None)[len(rest):])
    return Item(name, addr, size, access, default, lo, hi, unit, scale, offset, signed,
                dict(values) if values is not None else None)


def _table(m: ModelSpec) -> ControlTable:
    """One model's table: the SDK file's rows (address, size, name) typed by `_rules`, Indirect Address/Data
    expanded to the model's entry count."""
    rules = _rules(m, SERVOS[m.name])
    items: list[Item] = []
    indirect_address = indirect_data = None
    for addr, size, sdk_name in sdk_items(m.sdk_file):
        if sdk_name in _SDK_ALIASES:
            continue
        if sdk_name == "Indirect Address 1":
            indirect_address = addr
            continue
        if sdk_name == "Indirect Data 1":
            indirect_data = addr
            continue
        name = _SDK_NAMES.get(sdk_name, normalize_name(sdk_name))
        if name not in rules:
            raise ParameterError(f"{m.sdk_file}: item {sdk_name!r} has no typed rule in felis (controltable._rules)")
        items.append(_item(name, addr, size, rules[name]))
    indirect = None
    if indirect_address is not None and indirect_data is not None and m.indirect:
        a0, d0, count = indirect_address, indirect_data, m.indirect
        lo, hi = INDIRECT_TARGETS
        items += [Item(f"indirect_address_{n}", a0 + 2 * (n - 1), 2, "RW", d0 + n - 1, lo, hi)
                  for n in range(1, count + 1)]
        items += [Item(f"indirect_data_{n}", d0 + n - 1, 1, "RW", 0, 0, 255) for n in range(1, count + 1)]
        indirect = (a0, d0, count)
    return ControlTable(m.name, m.number, {it.name: it for it in items},
                        dict(rules["baud_rate"][8]), dict(rules["operating_mode"][8]), indirect=indirect)


CONTROL_TABLES: dict[str, ControlTable] = {m.name: _table(m) for m in MODELS}
_BY_NUMBER = {t.model_number: t for t in CONTROL_TABLES.values()}


def shared_item(*names: str) -> Item:
    """The item that every model having it has at one address and size, under one of ``names`` (alternatives:
    the XL430 has Present Load where the others have Present Current; the XW series has no LED). Code that
    addresses servos without knowing their model (group reads and writes, the emulator's hot path) takes
    addresses from here, by name, rather than as numbers. ParameterError if no model has it or the models disagree."""
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
    """The table for a model name (``"XL330-M288-T"``; case and the ``-T``/``-R`` suffix are free) or Model
    Number (``1200``). An unsupported model is a ParameterError of one line naming it (`unsupported`)."""
    if isinstance(model, int):
        table = _BY_NUMBER.get(model)
    else:
        table = CONTROL_TABLES.get(model) or CONTROL_TABLES.get(canonical_name(model) or "")
    if table is None:
        raise ParameterError(unsupported(model))
    return table


def unsupported(model: str | int) -> str:
    """One line on a model felis has no table for: its number or name, what the SDK calls it, where to look."""
    where = f"felis supports {len(CONTROL_TABLES)} Protocol 2.0 X-series models (docs/servos.md, `felis.servos.SERVOS`)"
    if isinstance(model, int):
        sdk = sdk_model_files().get(model)
        if sdk is not None:
            return f"Dynamixel Model Number {model} ({sdk.removesuffix('.model')}) is not supported: {where}"
        return f"unknown Dynamixel Model Number {model}: not in dynamixel-sdk's dynamixel.model either; {where}"
    return f"unknown Dynamixel model {model!r}: {where}"


def model_name(model_number: int) -> str:
    """Model name for a Model Number, or ``"unknown (N)"`` (``"unsupported mx_28 (30)"`` for a model the SDK
    knows and felis does not)."""
    t = _BY_NUMBER.get(model_number)
    if t:
        return t.model
    sdk = sdk_model_files().get(model_number)
    return f"unsupported {sdk.removesuffix('.model')} ({model_number})" if sdk else f"unknown ({model_number})"


decode_hardware_error = hardware_error_names
