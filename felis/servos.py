"""Servo datasheet figures the HAL and the simulator share.

Only performance numbers live here (stall torque, no-load speed, position resolution, default
position-controller gains). The byte-level control tables belong to ``felis.drivers``.
Sources: ROBOTIS e-Manual figures collected in ``shared/reference/dynamixel.md``.

Position resolution: 4096 ticks per turn, so one tick is 2π/4096 ≈ 1.534 mrad (0.088°). In position
mode (operating mode 3) the goal range is 0…4095 ticks, i.e. one turn; with the centre tick 2048
as zero, a joint can span at most [-π, π] rad around its zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TICKS_PER_REV = 4096
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
RPM_UNIT = 0.229  # Present/Goal Velocity unit (rev/min)
RAD_S_PER_VELOCITY_UNIT = RPM_UNIT * 2.0 * math.pi / 60.0  # ≈ 0.02398 rad/s
PWM_LIMIT = 885  # X-series PWM limit (full duty)


@dataclass(frozen=True)
class ServoModel:
    """Performance figures of one Dynamixel model.

    Attributes:
        name: the model name as ROBOTIS writes it, e.g. ``"XL330-M288-T"``.
        model_number: value of control-table item Model Number (addr 0).
        stall_torque: N·m at the nominal voltage.
        no_load_speed: rad/s at the nominal voltage.
        voltage: nominal supply voltage (V) the two figures above refer to.
        mass: kg.
        position_p_gain: factory Position P Gain (control-table units).
        position_d_gain: factory Position D Gain (control-table units).
    """

    name: str
    model_number: int
    stall_torque: float
    no_load_speed: float
    voltage: float
    mass: float
    position_p_gain: int
    position_d_gain: int

    @property
    def position_range(self) -> tuple[float, float]:
        """Joint-angle span (rad) reachable in position mode around the centre tick."""
        return (-math.pi, math.pi)


def _rpm(rpm: float) -> float:
    return rpm * 2.0 * math.pi / 60.0


SERVOS: dict[str, ServoModel] = {
    s.name: s
    for s in (
        ServoModel("XL330-M288-T", 1200, 0.52, _rpm(103), 5.0, 0.018, 400, 0),
        ServoModel("XL430-W250-T", 1060, 1.5, _rpm(57), 12.0, 0.0573, 640, 4000),
        ServoModel("XM430-W350-T", 1020, 4.1, _rpm(46), 12.0, 0.082, 800, 0),
    )
}


# Stall current (A) at the nominal voltage: Present Current -> torque with kt = stall_torque / stall_current.
# XL430-W250-T reports Present Load (fraction of stall torque) instead.
STALL_CURRENT_A = {"XL330-M288-T": 1.47, "XL430-W250-T": 1.4, "XM430-W350-T": 2.3}

# Hardware Error Status (addr 70) / Shutdown (addr 63) bit -> name
HARDWARE_ERROR_BITS = {0: "input_voltage", 2: "overheating", 3: "motor_encoder", 4: "electrical_shock",
                       5: "overload"}


def hardware_error_names(bits: int) -> list[str]:
    """Hardware Error Status bits -> names, e.g. ``0x20`` -> ``["overload"]``; unknown bits as ``bitN``."""
    return [HARDWARE_ERROR_BITS.get(b, f"bit{b}") for b in range(8) if bits >> b & 1]


def servo_model(name: str) -> ServoModel:
    """Look up a servo by model name; raises KeyError naming the known models."""
    try:
        return SERVOS[name]
    except KeyError:
        raise KeyError(f"unknown servo model {name!r}; known: {', '.join(SERVOS)}") from None
