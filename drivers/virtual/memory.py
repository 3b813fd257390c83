"""The control-table memory of an emulated servo: the addresses the emulator acts on, what a write touches.

Every address is taken from `felis.drivers.dynamixel.controltable` by item name (`address`): the emulator
runs on module-level ints in its hot path, but no number here is typed twice. A write is checked once per
(model, address, length) into a `WritePlan` (length and extent, then access; see the servo's rules in
`felis.drivers.virtual.instructions`), cached for every later write of the same shape. `hardware_bits` turns names
(``"overload"``) into Hardware Error Status bits, for fault injection and tests.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import EEPROM_END, HARDWARE_ERRORS, Item, address, shared_item
from felis.errors import ParameterError

# control-table addresses the emulator acts on
ID, BAUD, RETURN_DELAY, DRIVE_MODE, OPERATING_MODE, HOMING_OFFSET, MOVING_THRESHOLD = (
    address(n) for n in ("id", "baud_rate", "return_delay_time", "drive_mode", "operating_mode", "homing_offset",
                         "moving_threshold"))
FIRMWARE = address("firmware_version")
CURRENT_LIMIT, VELOCITY_LIMIT, MAX_POSITION, MIN_POSITION, SHUTDOWN = (
    address(n) for n in ("current_limit", "velocity_limit", "max_position_limit", "min_position_limit", "shutdown"))
TORQUE_ENABLE, STATUS_RETURN_LEVEL, REGISTERED, HARDWARE_ERROR, POSITION_P = (
    address(n) for n in ("torque_enable", "status_return_level", "registered_instruction", "hardware_error_status",
                         "position_p_gain"))
BUS_WATCHDOG, GOAL_PWM, GOAL_CURRENT, GOAL_VELOCITY, PROFILE_VELOCITY, GOAL_POSITION = (
    address(n) for n in ("bus_watchdog", "goal_pwm", "goal_current", "goal_velocity", "profile_velocity",
                         "goal_position"))
GOALS = frozenset((GOAL_PWM, GOAL_CURRENT, GOAL_VELOCITY, GOAL_POSITION))  # refused while the Bus Watchdog is tripped
WATCHDOG_UNIT_S = shared_item("bus_watchdog").scale
WATCHDOG_ERROR = 0xFF  # Bus Watchdog reads -1 once tripped
REALTIME_TICK, MOVING, PRESENT_CURRENT, PRESENT_POSITION, PRESENT_VOLTAGE, PRESENT_TEMPERATURE = (
    address(*n) for n in (("realtime_tick",), ("moving",), ("present_current", "present_load"), ("present_position",),
                          ("present_input_voltage",), ("present_temperature",)))
DYNAMIC_START = REALTIME_TICK  # items from here on are refreshed from the dynamics before a read
POSITION_MODES = (3, 4, 5)


@dataclass(frozen=True)
class WritePlan:
    """What a write of ``length`` bytes at ``addr`` touches, checked once per (model, addr, length)."""

    error: int  # structural error (length / range / access), 0 if none
    items: tuple[tuple[Item, int], ...] = ()  # (item, offset in the data)
    eeprom: bool = False
    addrs: frozenset[int] = frozenset()


_PLANS: dict[tuple[str, int, int], WritePlan] = {}


def write_plan(table, addr: int, length: int) -> WritePlan:
    """The (cached) plan of a write of ``length`` bytes at ``addr`` to a servo of this control table."""
    key = (table.model, addr, length)
    plan = _PLANS.get(key)
    if plan is None:
        plan = _PLANS[key] = _make_plan(table, addr, length)
    return plan


def _make_plan(table, addr: int, length: int) -> WritePlan:
    if length <= 0:
        return WritePlan(P.DATA_LENGTH_ERROR)
    if addr + length > table.size:
        return WritePlan(P.DATA_RANGE_ERROR)
    covered = sorted(table.covering(addr, length), key=lambda it: it.addr)
    if not covered:
        return WritePlan(P.DATA_RANGE_ERROR)
    if any(it.addr < addr or it.addr + it.size > addr + length for it in covered):
        return WritePlan(P.DATA_LENGTH_ERROR)
    if any(not it.writable for it in covered):
        return WritePlan(P.ACCESS_ERROR)
    return WritePlan(0, tuple((it, it.addr - addr) for it in covered), any(it.addr < EEPROM_END for it in covered),
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

