"""The servo model that system identification fits: its parameters, their bounds and datasheet values.

Each servo-driven joint is simulated (`felis.sim.servo`) as a position actuator with gain ``kp`` whose
force saturates at ``±torque_limit``, plus joint ``damping`` (back-EMF), ``armature`` (reflected rotor
inertia) and ``frictionloss`` (dry gear friction), on the MuJoCo model's link inertia and gravity::

    (I_link(q) + armature)·q̈ = clip(kp·(u − q), ±torque_limit) − damping·q̇ − friction(q̇) + τ_gravity(q) + …

The servo reports position, velocity and the motor torque ``effort = clip(kp·(u − q)) − damping·q̇``
(from Present Current).

`PARAMS` is the fitted vector, `BOUNDS` its search range as factors of the datasheet values
(`default_params`); `check_joints` checks joint names against a robot, `with_params` scales parameters.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

from felis.errors import SysidError
from felis.servos import servo_model
from felis.sim.servo import ServoParams, servo_params
from felis.spec import RobotSpec

PARAMS = ("kp", "damping", "armature", "frictionloss", "torque_limit")  # the fitted vector, in this order
# search range of each parameter, as factors (low, high) of its datasheet value
BOUNDS = {"kp": (0.2, 5.0), "damping": (0.1, 10.0), "armature": (0.05, 20.0), "frictionloss": (0.01, 20.0),
          "torque_limit": (0.3, 3.0)}


def default_params(spec: RobotSpec) -> dict[str, ServoParams]:
    """The datasheet servo model of every joint (what `MujocoRobot` uses without overrides)."""
    return {j.name: servo_params(servo_model(j.servo), m_per_rad=j.m_per_rad) for j in spec.joints}


def check_joints(spec: RobotSpec, joints: Sequence[str] | None) -> list[str]:
    """Joint names (all when None) checked against ``spec``; duplicates dropped, order kept."""
    if joints is None:
        return list(spec.names)
    out: list[str] = []
    for name in joints:
        if name not in spec.names:
            raise SysidError(f"{spec.name} has no joint {name!r}; joints: {', '.join(spec.names)}")
        if name not in out:
            out.append(name)
    if not out:
        raise SysidError("no joints to identify")
    return out


def with_params(params: Mapping[str, ServoParams], **factors: float) -> dict[str, ServoParams]:
    """Each of ``params`` with fields scaled, e.g. ``with_params(p, kp=1.4, damping=0.7)`` (tests, demos)."""
    return {n: replace(p, **{k: getattr(p, k) * f for k, f in factors.items()}) for n, p in params.items()}
