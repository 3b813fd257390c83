"""Control tables of every supported model, generated from dynamixel-sdk's tables (issue 23, item 1).

* every supported model: a virtual servo of it answers the real ``dynamixel-sdk`` over the pseudo-terminal with
  its Model Number, and one item reads and writes (one bus, all models);
* the generated tables of the three original models agree with the hand-typed tables felis had before
  (frozen below, `OLD_TABLES`: addresses, sizes and the typed metadata, item by item);
* model numbers and files agree with the SDK's ``dynamixel.model`` and with `felis.servos`;
* an unsupported model is one line naming it (the CLI's line: tests/cli/test_cli_models.py).
"""

from __future__ import annotations

import math

import pytest

from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.controltable import (
    BAUD_RATES,
    CENTRE_TICK,
    CONTROL_TABLES,
    INDIRECT_ADDRESS,
    INDIRECT_DATA,
    INDIRECT_TARGETS,
    OPERATING_MODES,
    STATE_BLOCK,
    ControlTable,
    Item,
    control_table,
    model_name,
)
from felis.drivers.dynamixel.models import MODELS, sdk_items, sdk_model_files
from felis.drivers.virtual import VirtualBus, VirtualServo
from felis.errors import ParameterError
from felis.servos import RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, SERVOS, emulated, servo_model

BAUD = 1_000_000
_PROFILE_ACC_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0


# ------------------------------------------------------------------ every model through the SDK
def test_every_supported_model_answers_the_sdk_and_reads_and_writes_an_item():
    numbers = [m.number for m in MODELS]
    with VirtualBus.for_models(numbers, baud=BAUD) as vb, \
            DynamixelBus(vb.port, BAUD, timeout_margin_ms=40, retries=2) as bus:
        for dxl_id, number in enumerate(numbers, start=1):
            found = bus.ping(dxl_id)
            assert (found.model_number, found.model) == (number, control_table(number).model)
            assert bus.read(dxl_id, "model_number", raw=True) == number
            table = bus.table(dxl_id)
            name = "led" if "led" in table.items else "position_p_gain"  # the XW series has no LED
            value = 1 if name == "led" else table.item(name).default + 7
            bus.write(dxl_id, name, value, raw=True)
            assert bus.read(dxl_id, name, raw=True) == value
            assert vb.servo(dxl_id).get(name) == value
            # the per-tick state block reads on every model, in SI
            assert bus.read(dxl_id, "present_position") == pytest.approx(0.0, abs=0.01)


def test_virtual_servos_of_every_model_boot_with_their_table():
    for m in MODELS:
        s = VirtualServo(m.name, 3)
        assert s.get("model_number") == m.number and s.get("id") == 3
        assert s.datasheet.stall_torque > 0 and s.datasheet.no_load_speed > 0  # datasheet or a flagged stand-in


# ------------------------------------------------------------------ the SDK files and the model list
def test_model_numbers_and_files_match_dynamixel_model_and_the_datasheets():
    files = sdk_model_files()
    assert len(MODELS) == len({m.number for m in MODELS}) == len(CONTROL_TABLES) == 31
    for m in MODELS:
        assert files[m.number] == m.sdk_file, m.name
        assert SERVOS[m.name].model_number == m.number
        assert control_table(m.number) is control_table(m.name) is CONTROL_TABLES[m.name]
    assert set(SERVOS) == set(CONTROL_TABLES)
    # every X-series file dynamixel.model names is supported
    x_files = {f for f in files.values() if f[0] in "x2" and f != "xl320.model"}
    assert x_files == {m.sdk_file for m in MODELS}


def test_addresses_and_sizes_are_the_sdk_files():
    for m in MODELS:
        t = CONTROL_TABLES[m.name]
        rows = {name: (addr, size) for addr, size, name in sdk_items(m.sdk_file)}
        for it in t.items.values():
            if it.name.startswith("indirect_"):
                continue
            sdk_name = "Secondary(Shadow) ID" if it.name == "secondary_id" else None
            match = [v for k, v in rows.items() if k == sdk_name or k.lower().replace(" ", "_") == it.name]
            assert match == [(it.addr, it.size)], (m.name, it.name)
        assert t.indirect[:2] == (rows["Indirect Address 1"][0], rows["Indirect Data 1"][0])
        assert STATE_BLOCK == (126, 10)


def test_per_model_differences_the_emanual_gives():
    xl330, xm430, xl430 = (control_table(n) for n in ("XL330-M077-T", "XM430-W350-T", "XL430-W250-T"))
    assert xl330.item("current_limit").scale == pytest.approx(0.001)
    assert xm430.item("current_limit").scale == pytest.approx(0.00269)
    assert control_table("XH430-V350-R").item("present_current").scale == pytest.approx(0.00134)
    assert "present_load" in xl430.items and "present_current" not in xl430.items
    assert "led" not in control_table("XW540-T260-R").items
    assert "external_port_mode_1" in control_table("XM540-W270-T").items
    assert 7 not in xl330.baud_rates and 7 in xm430.baud_rates
    assert xl330.indirect == (168, 224, 20) and xm430.indirect == (168, 224, 28)


def test_names_are_forgiving_and_datasheet_stand_ins_are_flagged():
    assert control_table("xm430-w350").model == "XM430-W350-T" == control_table("XM430-W350-R").model
    assert servo_model("xl330-m077").name == "XL330-M077-T"
    xl = SERVOS["XL330-M077-T"]
    assert (xl.stall_torque, round(xl.no_load_speed * 60 / (2 * math.pi)), xl.voltage) == (0.215, 383, 5.0)
    assert SERVOS["XC330-M181-T"].stall_torque == 0.60
    xd = SERVOS["XD430-T350-R"]
    assert xd.stall_torque is None and xd.stand_in
    assert emulated(xd.name).stall_torque == SERVOS[xd.stand_in].stall_torque
    assert all(s.source for s in SERVOS.values())


# ------------------------------------------------------------------ unknown models
def test_an_unsupported_model_is_one_line_naming_it():
    for model, fragment in ((9999, "9999"), (30, "mx_28"), ("XL999-Z000", "XL999-Z000")):
        with pytest.raises(ParameterError) as e:
            control_table(model)
        assert fragment in str(e.value) and "\n" not in str(e.value) and "docs/servos.md" in str(e.value)
        with pytest.raises(ParameterError):
            VirtualServo(model)
    assert model_name(9999) == "unknown (9999)" and "mx_28" in model_name(30)


# ------------------------------------------------------------------ the three original tables, frozen
def _old_table(model: str, *, firmware: int, current_unit_ma: float | None, baud_codes: range, modes: tuple[int, ...],
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


OLD_TABLES: dict[str, ControlTable] = {
    "XL330-M288-T": _old_table("XL330-M288-T", firmware=52, current_unit_ma=1.0, baud_codes=range(0, 7),
                           modes=(0, 1, 3, 4, 5, 16), voltage=(70, 35, 31, 70), temperature_limit=70,
                           velocity_limit=(445, 2047), current_limit=1750, gains=(0, 0, 400),
                           velocity_gains=(1000, 180), indirect=20),
    "XL430-W250-T": _old_table("XL430-W250-T", firmware=46, current_unit_ma=None, baud_codes=range(0, 8),
                           modes=(1, 3, 4, 16), voltage=(140, 60, 60, 140), temperature_limit=72,
                           velocity_limit=(265, 1023), current_limit=None, gains=(4000, 0, 640),
                           velocity_gains=(1000, 100), indirect=28),
    "XM430-W350-T": _old_table("XM430-W350-T", firmware=46, current_unit_ma=2.69, baud_codes=range(0, 8),
                           modes=(0, 1, 3, 4, 5, 16), voltage=(160, 95, 95, 160), temperature_limit=80,
                           velocity_limit=(200, 1023), current_limit=1193, gains=(0, 0, 800),
                           velocity_gains=(1920, 100), indirect=28),
}


@pytest.mark.parametrize("model", sorted(OLD_TABLES))
def test_generated_tables_agree_with_the_hand_typed_ones(model):
    old, new = OLD_TABLES[model], CONTROL_TABLES[model]
    assert (new.model, new.model_number, new.indirect) == (old.model, old.model_number, old.indirect)
    assert new.baud_rates == old.baud_rates and new.operating_modes == old.operating_modes
    for name, it in old.items.items():
        assert new.items[name] == it, name  # address, size, access, default, range, unit, scale, offset, sign
    added = set(new.items) - set(old.items)
    assert added <= {"pwm_slope"}, added  # the X330s' PWM Slope (62), which the SDK file lists
    old_mem, new_mem = old.defaults(), new.defaults()
    for name in added:
        it = new.items[name]
        old_mem[it.addr: it.addr + it.size] = it.encode(it.default)
    assert new_mem == old_mem
