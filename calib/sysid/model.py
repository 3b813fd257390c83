"""The servo model that system identification fits: its parameters, their bounds and starting values.

Each servo-driven joint is simulated as the firmware's position controller (`felis.sim.servo.controller`,
one implementation with the virtual bus's servos: `felis.drivers.virtual.horn`) on the joint::

    (I_link(q) + armature)·q̈ = clip(kp·e + ki·∫e dt − kd·q̇, ±torque_limit) − damping·q̇ − friction(q̇) + τ_gravity(q)

    kp = c·P/128    ki = c·I/65536/T    kd = c·D/16·T        (c = τ_stall·(4096/2π)/885, T = 1 ms)

with e = u − q, u the goal in force ``latency`` after it was written. The servo reports position, velocity and
the motor torque ``effort`` = the controller's clipped output − damping·q̇ (from Present Current).

`PARAMS` is the fitted vector per joint: the Position P, I, D Gain in control-table units (as the firmware
sees them), ``damping`` (back-EMF), ``armature`` (reflected rotor inertia), ``frictionloss`` (dry friction),
``torque_limit`` and ``latency`` (s). `BOUNDS` is its search range: factors of the starting value for the
parameters fitted on a log scale (`LOG`), multiples of `scale` for the others (which may be 0). Everything but
the latency lives in a `felis.sim.servo.ServoParams` (``pid`` holds P, I, D); `default_params` are the datasheet
servo at the description's gains; `with_gains` sets a joint's P, I, D (and kp with them).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

from felis.errors import SysidError
from felis.servos import servo_model
from felis.sim.servo import ServoParams, joint_gains, kp_from_gain, servo_params
from felis.spec import JointSpec, RobotSpec

PARAMS = ("p", "i", "d", "damping", "armature", "frictionloss", "torque_limit", "latency")  # fitted, in this order
GAINS = ("p", "i", "d")
LOG = ("p", "damping", "armature", "torque_limit")  # fitted as log(value / start); the others linearly from 0
# search range: (low, high) factors of the starting value for LOG, else multiples of `scale`
BOUNDS = {"p": (0.2, 5.0), "i": (0.0, 10.0), "d": (0.0, 20.0), "damping": (0.1, 10.0), "armature": (0.05, 20.0),
          "frictionloss": (0.0, 20.0), "torque_limit": (0.3, 3.0), "latency": (0.0, 20.0)}
LATENCY_SCALE_S = 0.001


def default_params(spec: RobotSpec) -> dict[str, ServoParams]:
    """The datasheet servo model of every joint at the description's P gain (what `MujocoRobot` uses without
    overrides); ``pid`` None: the description's gains."""
    out = {}
    for j in spec.joints:
        out[j.name] = servo_params(servo_model(j.servo), p_gain=joint_gains(j).p, m_per_rad=j.m_per_rad)
    return out


def gains(joint: JointSpec, params: ServoParams) -> tuple[float, float, float]:
    """(P, I, D) the model runs: ``params.pid``, else the description's."""
    if params.pid is not None:
        return tuple(float(g) for g in params.pid)
    g = joint_gains(joint)
    return (g.p, g.i, g.d)


def with_gains(joint: JointSpec, params: ServoParams, pid: Sequence[float]) -> ServoParams:
    """``params`` running Position P/I/D ``pid`` (control-table units); kp follows P."""
    p, i, d = (float(g) for g in pid)
    kp = kp_from_gain(servo_model(joint.servo), p) / joint.m_per_rad**2
    return replace(params, kp=kp, pid=(p, i, d))


def value(joint: JointSpec, params: ServoParams, latency_s: float, name: str) -> float:
    """Parameter ``name`` of `PARAMS` of a joint's model."""
    if name in GAINS:
        return gains(joint, params)[GAINS.index(name)]
    return float(latency_s) if name == "latency" else float(getattr(params, name))


def scale(joint: JointSpec, start: ServoParams, name: str) -> float:
    """The unit of a linearly fitted parameter (`BOUNDS` are multiples of it): I and D 100 at least (or their
    starting value), friction the datasheet's, latency 1 ms."""
    if name in ("i", "d"):
        return max(value(joint, start, 0.0, name), 100.0)
    if name == "frictionloss":
        return float(servo_params(servo_model(joint.servo), m_per_rad=joint.m_per_rad).frictionloss)
    if name == "latency":
        return LATENCY_SCALE_S
    return max(value(joint, start, 0.0, name), 1e-12)


def assemble(joint: JointSpec, base: ServoParams, values: Mapping[str, float]) -> tuple[ServoParams, float]:
    """(ServoParams, latency) from ``base`` with the parameters in ``values`` (names of `PARAMS`) replaced."""
    pid = [values.get(g, v) for g, v in zip(GAINS, gains(joint, base), strict=True)]
    p = with_gains(joint, base, pid)
    phys = {k: float(v) for k, v in values.items() if k not in GAINS and k != "latency"}
    return replace(p, **phys), float(values.get("latency", 0.0))


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
