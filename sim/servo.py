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

The rest of the firmware's controller (I, D, feedforward, the profile generator, modes 3/4/5 and 1) is
`felis.drivers.virtual.horn`'s, one implementation for the MuJoCo robots and the virtual bus's standalone
servos: ``kp`` here is its P term (what system identification fits), `controller` gives the whole
controller of a description's joint, `add_controller` / `configure_joint` put it into a model as MuJoCo
actuators (the integral through MuJoCo's ``pid`` actuator) that run inside the physics step.
For a prismatic joint driven through a transmission ``r`` (m per rad of horn): force = τ/r, so
``kp/r²``, ``τ_stall/r``, ``damping/r²`` and ``armature/r²``.
Readings are quantised as the servo reports them: positions to 4096 ticks per turn, velocities to
0.229 rpm units (`quantization_steps`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from felis.drivers.virtual.horn import (
    ARMATURE,
    FRICTION,
    Controller,
    Gains,
    JointActuators,
    Profile,
    add_controller,
    configure_joint,
    factory_current_limit,
    position_controller,
    profile_for,
)
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, TICKS_PER_REV, ServoModel, servo_model
from felis.spec import JointSpec

_ARMATURE, _FRICTION = ARMATURE, FRICTION
__all__ = ["Controller", "Gains", "JointActuators", "Profile", "ServoParams", "add_controller", "configure_joint",
           "controller", "joint_gains", "kp_from_gain", "profile_for", "quantization_steps", "servo_params"]


@dataclass(frozen=True)
class ServoParams:
    """MuJoCo-side parameters of one servo-driven joint (joint units: rad or m)."""

    kp: float  # N·m/rad: actuator gain
    torque_limit: float  # N·m: actuator forcerange
    damping: float  # N·m·s/rad: joint damping (back-EMF)
    armature: float  # kg·m²: joint armature (reflected rotor inertia)
    frictionloss: float  # N·m: joint dry friction
    # Position P/I/D Gain (control-table units) the servo runs, e.g. fitted by sysid; None: the description's.
    # When given, the controller's P, I and D come from it (``kp`` should then be P's stiffness, `kp_from_gain`).
    pid: tuple[float, float, float] | None = None

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


def joint_gains(joint: JointSpec) -> Gains:
    """The description's Position P/I/D and Feedforward gains, the model's factory values where not given."""
    f = Gains.factory(joint.servo)
    given = (*joint.pid, *joint.feedforward)
    return Gains(*(float(g) if g is not None else d for g, d in zip(given, (f.p, f.i, f.d, f.ff1, f.ff2), strict=True)))


def controller(joint: JointSpec, params: ServoParams | None = None) -> Controller:
    """The firmware controller of a description's joint, in joint units (rad or m): its gains (`joint_gains`),
    operating mode (5: capped at Goal Current's torque, default the Current Limit), through the transmission.
    ``params`` (e.g. fitted by sysid) overrides kp and the torque limit (before the mode-5 cap), and with its
    ``pid`` the P, I and D gains (then kp is P's)."""
    servo = servo_model(joint.servo)
    cap = None
    if joint.operating_mode == 5:
        cap = joint.goal_current if joint.goal_current is not None else factory_current_limit(joint.servo)
    gains = joint_gains(joint)
    if params is not None and params.pid is not None:
        gains = replace(gains, p=float(params.pid[0]), i=float(params.pid[1]), d=float(params.pid[2]))
    ctl = position_controller(servo, gains, current_limit_a=cap).through(joint.m_per_rad)
    if params is not None:
        limit = min(params.torque_limit, ctl.torque_limit) if joint.operating_mode == 5 else params.torque_limit
        kp = ctl.kp if params.pid is not None else params.kp
        ctl = Controller(kp, ctl.ki, ctl.kd, ctl.kff1, ctl.kff2, limit)
    return ctl

