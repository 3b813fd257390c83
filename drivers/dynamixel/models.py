"""Which Dynamixel models felis supports, where their tables are, and their per-model control-table figures.

Addresses and sizes are not here: `felis.drivers.dynamixel.controltable` reads them at run time from the
tables the installed ``dynamixel-sdk`` ships (``dynamixel_easy_sdk/control_table/*.model``, model number ->
file in ``dynamixel.model``; `sdk_table_dir`, `sdk_model_files`, `sdk_items`). What the SDK files lack —
access, units, ranges, factory defaults — is keyed by item name in `controltable`, and the per-model numbers
those rules need are the `ModelSpec` rows below (`MODELS`), from each model's ROBOTIS e-Manual control
table (https://emanual.robotis.com/docs/en/dxl/x/<model>/).

Supported: every Protocol 2.0 X-series model ``dynamixel.model`` lists (31): XL330-M077/M288, XC330-M181/
M288/T181/T288, XL430-W250, 2XL430-W250, XC430-W150/W240, 2XC430-W250, XM430-W210/W350, XH430-W210/W350,
XH430-V210/V350, XD430-T210/T350, XW430-T333, XM540-W150/W270, XH540-W150/W270, XH540-V150/V270,
XD540-T150/T270, XW540-T140/T260/H260. Model numbers are ``dynamixel.model``'s (checked by the tests).

Skipped, with the reason:

* ``mx_28``, ``mx_64``, ``mx_106`` (MX series: model numbers 30/311/321 are shared by the Protocol 1.0 and
  2.0 firmwares, other units and gains; not X-series), ``xl320`` (its own, different layout);
* ``ph*``/``pm*``/``h*``/``m*`` (DYNAMIXEL-P and PRO: other layout, units, resolution), ``ym*`` (Y series),
  ``rh_p12_rn`` (a gripper);
* ``xw430_t200.model``: not in ``dynamixel.model``, so the SDK cannot name its model number;
* the ``*_fw52.model`` variants of the X330 files: not in ``dynamixel.model``; they put Indirect Data 1 at 208,
  as today's e-Manual does (Indirect Address 1–20 at 168…206, Indirect Data 1–20 at 208…227), where the
  referenced files (and felis) say 224. felis follows ``dynamixel.model`` so the original XL330-M288-T table
  stays byte-identical; a real XL330/XC330 on current firmware may expect 208 (open question, see
  docs/servos.md).

Per-model figures marked ``checked=False`` were not read from that model's own e-Manual page: they are the
values of the named sibling (same family, same case), listed in ``note``.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

from felis.errors import ParameterError

SDK_PACKAGE = "dynamixel_easy_sdk"  # ships the tables; found by path, not imported


@dataclass(frozen=True)
class ModelSpec:
    """The per-model figures the item rules in `controltable` need (raw control-table units).

    ``current_unit_ma``: Present/Goal Current and Current Limit unit in mA; None: the model has no current
    sensing and address 126 is Present Load. ``voltage``: (Max Voltage Limit default, Min Voltage Limit default,
    range low, range high) in 0.1 V. ``velocity_limit``: (default, range high) in 0.229 rev/min. ``gains``:
    Position (D, I, P); ``velocity_gains``: Velocity (I, P). ``indirect``: entries in the first Indirect
    Address/Data bank (the second bank at 578/634 is not modelled). ``firmware``: the Firmware Version the
    emulator reports (not a factory value). ``extra``: defaults of other items that differ from the rules'.
    """

    name: str
    number: int
    sdk_file: str
    current_unit_ma: float | None
    current_limit: int | None
    velocity_limit: tuple[int, int]
    voltage: tuple[int, int, int, int]
    gains: tuple[int, int, int]
    velocity_gains: tuple[int, int]
    temperature_limit: int = 80
    baud_codes: range = range(0, 8)
    modes: tuple[int, ...] = (0, 1, 3, 4, 5, 16)
    indirect: int = 28
    firmware: int = 46
    pwm_slope: tuple[int, float] | None = None  # (default, V/s per unit) where the model has PWM Slope
    extra: dict[str, int] = field(default_factory=dict)
    checked: bool = True
    note: str = ""


_X330 = dict(temperature_limit=70, baud_codes=range(0, 7), indirect=20, firmware=52)
_NO_CURRENT = dict(current_unit_ma=None, current_limit=None, modes=(1, 3, 4, 16))
_5V = (70, 35, 31, 70)
_11V = (140, 55, 55, 140)
_12V = (160, 95, 95, 160)
_24V = (300, 110, 110, 300)


def _m(name: str, number: int, sdk_file: str, **kw) -> ModelSpec:
    return ModelSpec(name, number, sdk_file, **kw)


MODELS: tuple[ModelSpec, ...] = (
    # ---- X330 (1 mA current unit, 20 indirect entries, no 4.5 Mbps)
    _m("XL330-M288-T", 1200, "xl330_m288.model", current_unit_ma=1.0, current_limit=1750, velocity_limit=(445, 2047),
       voltage=_5V, gains=(0, 0, 400), velocity_gains=(1000, 180), pwm_slope=(140, 1.977),
       note="the original hand-typed table; PWM Slope (new) as on the XL330-M077 page", **_X330),
    _m("XL330-M077-T", 1190, "xl330_m077.model", current_unit_ma=1.0, current_limit=1750,
       velocity_limit=(1620, 2047), voltage=_5V, gains=(0, 400, 400), velocity_gains=(400, 40),
       pwm_slope=(140, 1.977), extra={"shutdown": 53}, **_X330),
    _m("XC330-M181-T", 1230, "xc330_m181.model", current_unit_ma=1.0, current_limit=2352, velocity_limit=(545, 2047),
       voltage=_5V, gains=(500, 0, 1200), velocity_gains=(1400, 100), pwm_slope=(140, 1.977), **_X330),
    _m("XC330-M288-T", 1240, "xc330_m288.model", current_unit_ma=1.0, current_limit=2352, velocity_limit=(350, 2047),
       voltage=_5V, gains=(500, 0, 1100), velocity_gains=(1600, 50), pwm_slope=(140, 1.977), **_X330),
    _m("XC330-T181-T", 1210, "xc330_t181.model", current_unit_ma=1.0, current_limit=910, velocity_limit=(510, 2047),
       voltage=_11V, gains=(0, 0, 900), velocity_gains=(1200, 40), pwm_slope=(255, 3.955), **_X330),
    _m("XC330-T288-T", 1220, "xc330_t288.model", current_unit_ma=1.0, current_limit=910, velocity_limit=(320, 2047),
       voltage=_11V, gains=(0, 0, 900), velocity_gains=(1200, 40), pwm_slope=(255, 3.955), **_X330),
    # ---- X430 without current sensing (Present Load)
    _m("XL430-W250-T", 1060, "xl430_w250.model", velocity_limit=(265, 1023), voltage=(140, 60, 60, 140),
       gains=(4000, 0, 640), velocity_gains=(1000, 100), temperature_limit=72, **_NO_CURRENT),  # original table
    _m("2XL430-W250-T", 1090, "2xl430_w250.model", velocity_limit=(265, 1023), voltage=(140, 60, 60, 140),
       gains=(4000, 0, 640), velocity_gains=(1000, 100), temperature_limit=72, checked=False,
       note="XL430-W250-T's values", **_NO_CURRENT),
    _m("XC430-W150-T", 1070, "xc430_w150.model", velocity_limit=(460, 1023), voltage=(160, 60, 60, 160),
       gains=(0, 0, 460), velocity_gains=(1920, 100), extra={"moving_threshold": 20}, **_NO_CURRENT),
    _m("XC430-W240-T", 1080, "xc430_w240.model", velocity_limit=(460, 1023), voltage=(160, 60, 60, 160),
       gains=(0, 0, 460), velocity_gains=(1920, 100), extra={"moving_threshold": 20}, checked=False,
       note="XC430-W150-T's values", **_NO_CURRENT),
    _m("2XC430-W250-T", 1160, "2xc430_w250.model", velocity_limit=(460, 1023), voltage=(160, 60, 60, 160),
       gains=(0, 0, 460), velocity_gains=(1920, 100), extra={"moving_threshold": 20}, checked=False,
       note="XC430-W150-T's values", **_NO_CURRENT),
    # ---- X430 with current sensing (2.69 mA; XH430-V: 1.34 mA)
    _m("XM430-W350-T", 1020, "xm430_w350.model", current_unit_ma=2.69, current_limit=1193, velocity_limit=(200, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100)),  # the original hand-typed table
    _m("XM430-W210-T", 1030, "xm430_w210.model", current_unit_ma=2.69, current_limit=1193, velocity_limit=(330, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XH430-W350-T", 1000, "xh430_w350.model", current_unit_ma=2.69, current_limit=648, velocity_limit=(130, 1023),
       voltage=_12V, gains=(0, 0, 900), velocity_gains=(1920, 100)),
    _m("XH430-W210-T", 1010, "xh430_w210.model", current_unit_ma=2.69, current_limit=648, velocity_limit=(130, 1023),
       voltage=_12V, gains=(0, 0, 900), velocity_gains=(1920, 100), checked=False, note="XH430-W350-T's values"),
    _m("XD430-T350-R", 1001, "xd430_t350.model", current_unit_ma=2.69, current_limit=648, velocity_limit=(130, 1023),
       voltage=_12V, gains=(0, 0, 900), velocity_gains=(1920, 100), checked=False, note="XH430-W350-T's values"),
    _m("XD430-T210-R", 1011, "xd430_t210.model", current_unit_ma=2.69, current_limit=648, velocity_limit=(130, 1023),
       voltage=_12V, gains=(0, 0, 900), velocity_gains=(1920, 100), checked=False, note="XH430-W350-T's values"),
    _m("XH430-V350-R", 1040, "xh430_v350.model", current_unit_ma=1.34, current_limit=689, velocity_limit=(285, 1023),
       voltage=_24V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XH430-V210-R", 1050, "xh430_v210.model", current_unit_ma=1.34, current_limit=689, velocity_limit=(285, 1023),
       voltage=_24V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XH430-V350-R's values"),
    _m("XW430-T333-R", 1270, "xw430_t333.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(139, 1023),
       voltage=_12V, gains=(0, 0, 900), velocity_gains=(1920, 100)),
    # ---- X540 (2.69 mA, Current Limit 2047)
    _m("XM540-W270-T", 1120, "xm540_w270.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(128, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XM540-W150-T", 1130, "xm540_w150.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(128, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False,
       note="XM540-W270-T's values (gains and Current Limit also on the 2018 XM540-W150 datasheet)"),
    _m("XH540-W270-T", 1100, "xh540_w270.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XH540-W150-T", 1110, "xh540_w150.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XH540-W270-T's values"),
    _m("XH540-V270-R", 1140, "xh540_v270.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(128, 1023),
       voltage=_24V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XH540-V150-R", 1150, "xh540_v150.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(128, 1023),
       voltage=_24V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XH540-V270-R's values"),
    _m("XD540-T270-R", 1101, "xd540_t270.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100),
       note="its e-Manual page gives Model Number 1100 (copied from XH540-W270); dynamixel.model's 1101 is used"),
    _m("XD540-T150-R", 1111, "xd540_t150.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XD540-T270-R's values"),
    _m("XW540-T260-R", 1170, "xw540_t260.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100)),
    _m("XW540-T140-R", 1180, "xw540_t140.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XW540-T260-R's values"),
    _m("XW540-H260-R", 1310, "xw540_h260.model", current_unit_ma=2.69, current_limit=2047, velocity_limit=(167, 1023),
       voltage=_12V, gains=(0, 0, 800), velocity_gains=(1920, 100), checked=False, note="XW540-T260-R's values"),
)


@cache
def sdk_table_dir() -> Path:
    """The folder of the SDK's ``*.model`` files (located without importing the package)."""
    spec = importlib.util.find_spec(SDK_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise ParameterError(f"the {SDK_PACKAGE} package (part of dynamixel-sdk >= 4) is not installed: it ships the "
                             "control tables felis reads; `pip install dynamixel-sdk`")
    return Path(next(iter(spec.submodule_search_locations))) / "control_table"


@cache
def sdk_model_files() -> dict[int, str]:
    """``dynamixel.model``: Model Number -> table file name, for every model the SDK knows."""
    out = {}
    for line in (sdk_table_dir() / "dynamixel.model").read_text(encoding="utf-8").splitlines()[1:]:
        parts = line.split("\t")
        if len(parts) >= 2 and parts[0].strip().isdigit():
            out[int(parts[0])] = parts[1].strip()
    return out


@cache
def sdk_items(filename: str) -> tuple[tuple[int, int, str], ...]:
    """The ``[control table]`` section of one SDK file: (address, size, data name) rows, in file order."""
    rows, inside = [], False
    for line in (sdk_table_dir() / filename).read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line.startswith("["):
            inside = line == "[control table]"
            continue
        parts = line.split("\t")
        if inside and len(parts) >= 3 and parts[0].isdigit():
            rows.append((int(parts[0]), int(parts[1]), parts[2].strip()))
    return tuple(rows)
