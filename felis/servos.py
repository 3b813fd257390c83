"""Servo datasheet figures the HAL and the simulator share.

Only performance numbers live here (stall torque, stall current, no-load speed, nominal voltage, mass,
gear ratio, factory position-controller gains). The byte-level control tables belong to
``felis.drivers.dynamixel`` (`controltable`, `models`), which take the factory P/D gains from here.

Sources: the ROBOTIS e-Manual specification table of each model (https://emanual.robotis.com/docs/en/dxl/x/
<model>/, whose figures live in the e-Manual repository's ``_data/dxl_x_info.yml``), read for this table in
2025; each entry's ``source`` names its page. Figures are quoted at the e-Manual's recommended voltage
(the bold row), except XL430-W250-T, whose entry predates this table (below). Where the e-Manual gives no
specification table we could read (XD430-T210/T350, XD540-T150/T270, XW430-T333, XW540-H260), the figures
are ``None`` and ``stand_in`` names the model whose figures the emulator borrows (`emulated`): an
assumption, flagged as such, never a datasheet value. The mass is the datasheet's, the 2XL430/2XC430 mass is
that of the two-axis unit.

Notes on the three original entries (kept unchanged, byte for byte): XL430-W250-T quotes 1.5 N·m / 1.4 A
(at 12 V) with 57 rev/min, which the e-Manual gives at 11.1 V (61 rev/min at 12 V); its mass 57.3 g vs the
e-Manual's 57.2 g.

Position resolution: 4096 ticks per turn, so one tick is 2π/4096 ≈ 1.534 mrad (0.088°). In position
mode (operating mode 3) the goal range is 0…4095 ticks, i.e. one turn; with the centre tick 2048
as zero, a joint can span at most [-π, π] rad around its zero.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

TICKS_PER_REV = 4096
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
RPM_UNIT = 0.229  # Present/Goal Velocity unit (rev/min)
RAD_S_PER_VELOCITY_UNIT = RPM_UNIT * 2.0 * math.pi / 60.0  # ≈ 0.02398 rad/s
PWM_LIMIT = 885  # X-series PWM limit (full duty)

_EMANUAL = "ROBOTIS e-Manual, https://emanual.robotis.com/docs/en/dxl/x/"


@dataclass(frozen=True)
class ServoModel:
    """Performance figures of one Dynamixel model.

    Attributes:
        name: the model name as ROBOTIS writes it, e.g. ``"XL330-M288-T"``.
        model_number: value of control-table item Model Number (addr 0).
        stall_torque: N·m at the nominal voltage (None: not known, see ``stand_in``).
        no_load_speed: rad/s at the nominal voltage (None: not known).
        voltage: nominal supply voltage (V) the figures refer to (None: not known).
        mass: kg (None: not known).
        position_p_gain: factory Position P Gain (control-table units).
        position_d_gain: factory Position D Gain (control-table units).
        gear_ratio: reduction n:1 (None: not known).
        stall_current: A at the nominal voltage (None: not known).
        source: where the figures come from.
        stand_in: for a model whose figures are unknown, the model the emulator borrows them from.
    """

    name: str
    model_number: int
    stall_torque: float | None
    no_load_speed: float | None
    voltage: float | None
    mass: float | None
    position_p_gain: int
    position_d_gain: int
    gear_ratio: float | None = None
    stall_current: float | None = None
    source: str = ""
    stand_in: str | None = None

    @property
    def position_range(self) -> tuple[float, float]:
        """Joint-angle span (rad) reachable in position mode around the centre tick."""
        return (-math.pi, math.pi)

    @property
    def figures_known(self) -> bool:
        """True when stall torque, no-load speed and voltage come from the datasheet."""
        return None not in (self.stall_torque, self.no_load_speed, self.voltage)


def _rpm(rpm: float) -> float:
    return rpm * 2.0 * math.pi / 60.0


def _x(name: str, number: int, torque: float | None, rpm: float | None, volts: float | None, grams: float | None,
       p: int, d: int, ratio: float | None, amps: float | None, page: str, stand_in: str | None = None) -> ServoModel:
    """One e-Manual row: figures at ``volts``; ``page`` is the e-Manual page name (``xm430-w350``)."""
    return ServoModel(name, number, torque, None if rpm is None else _rpm(rpm), volts,
                      None if grams is None else grams / 1000.0, p, d, ratio, amps, _EMANUAL + page, stand_in)


_UNKNOWN = "figures not in the e-Manual pages available to us; "

SERVOS: dict[str, ServoModel] = {
    s.name: s
    for s in (
        # the three original entries, unchanged (module doc)
        ServoModel("XL330-M288-T", 1200, 0.52, _rpm(103), 5.0, 0.018, 400, 0, 288.4, 1.47, _EMANUAL + "xl330-m288"),
        ServoModel("XL430-W250-T", 1060, 1.5, _rpm(57), 12.0, 0.0573, 640, 4000, 258.5, 1.4,
                   _EMANUAL + "xl430-w250 (1.5 N·m, 1.4 A at 12 V; 57 rev/min is the 11.1 V figure)"),
        ServoModel("XM430-W350-T", 1020, 4.1, _rpm(46), 12.0, 0.082, 800, 0, 353.5, 2.3, _EMANUAL + "xm430-w350"),
        # X330: 5 V (M) or 11.1 V (T) recommended
        _x("XL330-M077-T", 1190, 0.215, 383, 5.0, 18, 400, 0, 77.5, 1.47, "xl330-m077"),
        _x("XC330-M181-T", 1230, 0.60, 129, 5.0, 23, 1200, 500, 180.62, 1.80, "xc330-m181"),
        _x("XC330-M288-T", 1240, 0.93, 81, 5.0, 23, 1100, 500, 288.35, 1.80, "xc330-m288"),
        _x("XC330-T181-T", 1210, 0.76, 104, 11.1, 23, 900, 0, 180.62, 0.80, "xc330-t181"),
        _x("XC330-T288-T", 1220, 0.92, 65, 11.1, 23, 900, 0, 288.35, 0.80, "xc330-t288"),
        # X430 without current sensing (Present Load)
        _x("2XL430-W250-T", 1090, 1.4, 57, 11.1, 98.2, 640, 4000, 257.4, 1.3, "2xl430-w250"),
        _x("XC430-W150-T", 1070, 1.6, 106, 12.0, 65, 460, 0, 159.59, 1.4, "xc430-w150"),
        _x("XC430-W240-T", 1080, 1.9, 70, 12.0, 65, 460, 0, 245.22, 1.4, "xc430-w240 (gains: XC430-W150's)"),
        _x("2XC430-W250-T", 1160, 1.8, 64, 12.0, 102, 460, 0, 257.4, 1.4, "2xc430-w250 (gains: XC430-W150's)"),
        # X430 with current sensing
        _x("XM430-W210-T", 1030, 3.0, 77, 12.0, 82, 800, 0, 212.6, 2.3, "xm430-w210"),
        _x("XH430-W210-T", 1010, 2.5, 50, 12.0, 82, 900, 0, 212.6, 1.3, "xh430-w210 (gains: XH430-W350's)"),
        _x("XH430-W350-T", 1000, 3.4, 30, 12.0, 82, 900, 0, 353.5, 1.3, "xh430-w350"),
        _x("XH430-V210-R", 1050, 2.6, 52, 24.0, 82, 800, 0, 212.6, 0.7, "xh430-v210 (gains: XH430-V350's)"),
        _x("XH430-V350-R", 1040, 3.3, 31, 24.0, 82, 800, 0, 353.5, 0.7, "xh430-v350"),
        _x("XD430-T210-R", 1011, None, None, None, None, 900, 0, None, None,
           "xd430-t210 (" + _UNKNOWN + "gains: XH430-W350's)", stand_in="XH430-W210-T"),
        _x("XD430-T350-R", 1001, None, None, None, None, 900, 0, None, None,
           "xd430-t350 (" + _UNKNOWN + "gains: XH430-W350's)", stand_in="XH430-W350-T"),
        _x("XW430-T333-R", 1270, None, None, None, None, 900, 0, None, None, "xw430-t333 (" + _UNKNOWN + ")",
           stand_in="XM430-W350-T"),
        # X540
        _x("XM540-W150-T", 1130, 7.3, 53, 12.0, 165, 800, 0, 152.3, 4.4, "xm540-w150"),
        _x("XM540-W270-T", 1120, 10.6, 30, 12.0, 165, 800, 0, 272.5, 4.4, "xm540-w270"),
        _x("XH540-W150-T", 1110, 7.1, 70, 12.0, 165, 800, 0, 152.3, 4.9, "xh540-w150 (gains: XH540-W270's)"),
        _x("XH540-W270-T", 1100, 9.9, 39, 12.0, 165, 800, 0, 272.5, 4.9, "xh540-w270"),
        _x("XH540-V150-R", 1150, 6.4, 60, 24.0, 165, 800, 0, 152.3, 2.4, "xh540-v150 (gains: XH540-V270's)"),
        _x("XH540-V270-R", 1140, 9.2, 34, 24.0, 165, 800, 0, 272.5, 2.4, "xh540-v270"),
        _x("XD540-T150-R", 1111, None, None, None, None, 800, 0, None, None,
           "xd540-t150 (" + _UNKNOWN + "gains: XD540-T270's)", stand_in="XH540-W150-T"),
        _x("XD540-T270-R", 1101, None, None, None, None, 800, 0, None, None, "xd540-t270 (" + _UNKNOWN + ")",
           stand_in="XH540-W270-T"),
        _x("XW540-T140-R", 1180, 6.9, 72, 12.0, 185, 800, 0, 145.6, 4.9, "xw540-t140 (gains: XW540-T260's)"),
        _x("XW540-T260-R", 1170, 9.5, 40, 12.0, 185, 800, 0, 260.6, 4.9, "xw540-t260"),
        _x("XW540-H260-R", 1310, None, None, None, None, 800, 0, None, None,
           "xw540-h260 (" + _UNKNOWN + "gains: XW540-T260's)", stand_in="XW540-T260-R"),
    )
}


# Stall current (A) at the nominal voltage: Present Current -> torque with kt = stall_torque / stall_current.
# XL430-W250-T (and the other models without current sensing) report Present Load (fraction of stall torque).
STALL_CURRENT_A = {s.name: s.stall_current for s in SERVOS.values() if s.stall_current is not None}

# Hardware Error Status (addr 70) / Shutdown (addr 63) bit -> name
HARDWARE_ERROR_BITS = {0: "input_voltage", 2: "overheating", 3: "motor_encoder", 4: "electrical_shock",
                       5: "overload"}


def hardware_error_names(bits: int) -> list[str]:
    """Hardware Error Status bits -> names, e.g. ``0x20`` -> ``["overload"]``; unknown bits as ``bitN``."""
    return [HARDWARE_ERROR_BITS.get(b, f"bit{b}") for b in range(8) if bits >> b & 1]


def canonical_name(name: str) -> str | None:
    """The `SERVOS` key for a model name in any common spelling: case, and the interface suffix (``-T``, ``-R``,
    ``-T/R``, none) are ignored, so ``"xm430-w350"`` and ``"XM430-W350-R"`` find ``"XM430-W350-T"``."""
    def base(n: str) -> str:
        n = n.strip().upper()
        for suffix in ("-T/R", "-T", "-R"):
            if n.endswith(suffix):
                return n[: -len(suffix)]
        return n

    want = base(name)
    return next((k for k in SERVOS if base(k) == want), None)


def velocity_lag_s(servo: ServoModel, p_gain: float | None = None) -> float:
    """How far behind (s) a position-mode servo follows a goal that moves at constant speed, unloaded: the P term
    must supply the duty that cancels the back-EMF, PWM = KPP·e = 885·ω/ω₀, so e = (885·128/(P·ω₀))·ω in ticks,
    i.e. a lag of 885·128/(P·ω₀·4096/2π) seconds (XM430-W350 at P = 800: 45 ms). The I term removes it only
    slowly; a host that streams a known path can command that much ahead (`felis.controllers.arm_track`)."""
    gain = servo.position_p_gain if p_gain is None else p_gain
    if not (servo.no_load_speed and gain and gain > 0):
        return 0.0
    return PWM_LIMIT * 128.0 / (gain * servo.no_load_speed * TICKS_PER_REV / (2.0 * math.pi))


def servo_model(name: str) -> ServoModel:
    """Look up a servo by model name (any spelling `canonical_name` accepts); raises KeyError naming the
    known models."""
    key = name if name in SERVOS else canonical_name(name)
    if key is None:
        raise KeyError(f"unknown servo model {name!r}; known: {', '.join(SERVOS)}")
    return SERVOS[key]


def emulated(name: str) -> ServoModel:
    """The figures an emulator uses for a model: its datasheet's, or, where they are unknown, its ``stand_in``'s
    under its own name, number and gains (an assumption the module doc lists)."""
    s = servo_model(name)
    if s.figures_known or s.stand_in is None:
        return s
    t = SERVOS[s.stand_in]
    return dataclasses.replace(s, stall_torque=t.stall_torque, no_load_speed=t.no_load_speed, voltage=t.voltage,
                               stall_current=t.stall_current)
