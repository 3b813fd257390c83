"""Dynamixel position servo, as MuJoCo actuator and joint parameters.

The X-series position controller drives the motor with a PWM duty ``u`` (±885 = full duty) from the
position error in ticks, ``u = K_PP · e_ticks`` with ``K_PP = P_gain / 128`` (ROBOTIS e-Manual,
"Position PID Gain"). A geared DC motor at duty ``d = u/885`` gives

    τ = τ_stall · clip(d, -1, 1) − (τ_stall / ω_no_load) · ω

so the servo is modelled as

* a MuJoCo position actuator with ``kp = τ_stall · K_PP · (4096 / 2π) / 885`` (N·m/rad) whose force
  is clamped to ``±τ_stall`` (``forcerange``): the saturation at the stall torque;
* joint ``damping = τ_stall / ω_no_load`` (back-EMF, not clamped), which caps the speed at the
  no-load speed under full duty: the velocity limit;
* ``armature`` (reflected rotor inertia) and ``frictionloss`` (gear friction), rough datasheet-scale
  values that system identification refines.

The D and I terms and the profile generator are not modelled (factory D/I are 0 on XL330/XM430).
For a prismatic joint driven through a transmission ``r`` (m per rad of horn): force = τ/r, so
``kp/r²``, ``τ_stall/r``, ``damping/r²`` and ``armature/r²``.
Readings are quantised as the servo reports them: positions to 4096 ticks per turn, velocities to
0.229 rpm units (`quantization_steps`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, TICKS_PER_REV, ServoModel

# Rough reflected rotor inertia (kg·m²) and gear friction (N·m) per model, refined by sysid.
_ARMATURE = {"XL330-M288-T": 5e-4, "XL430-W250-T": 5e-3, "XM430-W350-T": 1e-2}
_FRICTION = {"XL330-M288-T": 0.005, "XL430-W250-T": 0.01, "XM430-W350-T": 0.02}


@dataclass(frozen=True)
class ServoParams:
    """MuJoCo-side parameters of one servo-driven joint (joint units: rad or m)."""

    kp: float  # N·m/rad: actuator gain
    torque_limit: float  # N·m: actuator forcerange
    damping: float  # N·m·s/rad: joint damping (back-EMF)
    armature: float  # kg·m²: joint armature (reflected rotor inertia)
    frictionloss: float  # N·m: joint dry friction

    def through(self, m_per_rad: float) -> ServoParams:
        """The same servo seen through a transmission of ``m_per_rad`` (prismatic joint)."""
        r = m_per_rad
        return replace(self, kp=self.kp / r**2, torque_limit=self.torque_limit / r,
                       damping=self.damping / r**2, armature=self.armature / r**2,
                       frictionloss=self.frictionloss / r)


def kp_from_gain(servo: ServoModel, p_gain: float) -> float:
    """Position P gain (control-table units) → stiffness in N·m/rad (before saturation)."""
    return servo.stall_torque * (p_gain / 128.0) * (TICKS_PER_REV / (2.0 * math.pi)) / PWM_LIMIT


def servo_params(servo: ServoModel, p_gain: float | None = None, m_per_rad: float = 1.0) -> ServoParams:
    """Parameters for ``servo`` at ``p_gain`` (default: the factory gain)."""
    gain = servo.position_p_gain if p_gain is None else p_gain
    if not (math.isfinite(gain) and gain >= 0):
        raise ValueError(f"P gain must be a non-negative number, got {gain}")
    params = ServoParams(
        kp=kp_from_gain(servo, gain),
        torque_limit=servo.stall_torque,
        damping=servo.stall_torque / servo.no_load_speed,
        armature=_ARMATURE.get(servo.name, 1e-3),
        frictionloss=_FRICTION.get(servo.name, 0.01),
    )
    return params if m_per_rad == 1.0 else params.through(m_per_rad)


def quantization_steps(m_per_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Resolution of the servo's readings in joint units: (position step, velocity step).

    One encoder tick (2π/4096 rad of horn) and one Present Velocity unit (0.229 rpm of horn),
    times the transmission. `MujocoRobot` rounds its readings to these steps.
    """
    m = np.asarray(m_per_rad, dtype=float)
    return RAD_PER_TICK * m, RAD_S_PER_VELOCITY_UNIT * m
