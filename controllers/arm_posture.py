"""The arm's posture rule: the joint angles a demonstrator gives a tool-point path (seed 001 §3.1).

A tool point alone leaves the tool pitch φ free (`armkin`); the demonstrator fixes it by a posture rule
(`posture_pitch`), a smooth function of the target and of its vertical velocity (a person leads with the
tool), and solves the closed form on the elbow-up branch (`demo_joints`). The learned IK
(`felis.learning.ik`) is trained to imitate it; the builtin trajectories (`felis.controllers.trajectories`)
carry its angles.

**Workspace** of the demonstrations (`in_workspace`): d = |p − S| / REACH ≤ 0.92, horizontal distance
from the joint1 axis r ≥ 0.08 m, z ≥ 0.03 m, and the rule's pose within the joint limits by 0.05 rad
with the elbow at least 0.15 rad from stretched (δ ≥ 0.15, away from the singular straight arm).
Units: metres, seconds, radians.
"""

from __future__ import annotations

import numpy as np

from felis import armkin
from felis.armkin import REACH, SHOULDER
from felis.errors import TrajectoryError

DT = 0.01  # s: paths (demonstrations, trajectories) are sampled at 100 Hz

# --- the posture rule (see posture_pitch)
PHI_DOWN = 1.2  # rad (68.8°): tool pitch for a close target at shoulder height
K_HEIGHT = 2.0  # rad per REACH of height: close targets tip the tool up as they rise
K_LEAD, V_LEAD = 0.3, 0.15  # rad, m/s: the tool leads vertical motion by up to K_LEAD (tanh(−v_z/V_LEAD))
D_NEAR, D_FAR = 0.25, 1.0  # blend from "pointing down" (d ≤ D_NEAR) to "along the reach" (d ≥ D_FAR)

# --- the demonstration workspace and motion bounds
D_MAX = 0.92  # max |p − S| / REACH
R_MIN = 0.08  # m: min horizontal distance from the joint1 axis
Z_MIN = 0.03  # m: min height above the base plate
LIMIT_MARGIN = 0.05  # rad inside the joint limits
DELTA_MIN = 0.15  # rad: min elbow angle δ (the straight arm, δ = 0, is singular)


def smootherstep(x: np.ndarray) -> np.ndarray:
    """s(x) = x³ (10 − 15 x + 6 x²) on x clipped to [0, 1]: 0 → 1 with s' = s'' = 0 at both ends (C²).

    Also the minimum-jerk progress profile of a rest-to-rest move."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def posture_pitch(target: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
    """The demonstrator's tool pitch φ (rad; 0 = level, positive = down) for targets (..., 3) moving at
    ``velocity`` (..., 3) m/s (None: at rest).

    With rel = target − S, r = |rel_xy| (horizontal distance from the joint1 axis), h = rel_z, v_z the
    vertical velocity::

        d = |rel| / REACH,   ε = atan2(h, r)   (elevation of the shoulder → target line)
        w = smootherstep((d − 0.25) / 0.75)
        φ = (1 − w) (1.2 − 2.0 h / REACH + 0.3 tanh(−v_z / 0.15)) + w (−ε)

    What a person does: a far reach points the tool along the reach direction (φ → −ε as d → 1); a
    close target is approached from above with the tool pointing down (φ ≈ 1.2 rad at shoulder
    height, ≈ 1.45 rad at table height), tipping up as the close target rises (the height term).
    The blend is C² (smootherstep) and ε is smooth away from the joint1 axis, so φ has no kinks in
    the workspace (r ≥ 0.08 m). The constants were chosen on a grid over the workspace (`in_workspace`)
    to maximise the smallest distance of φ to the infeasible pitches: ≥ 0.34 rad everywhere (5 mm grid)
    at rest. The lead term: moving down, a person points the tool further down, moving up tips it up,
    by up to 0.3 rad (17°; 0.17 rad at 0.1 m/s), smoothly saturating, fading out at full reach where the
    pitch has no freedom left. It makes the posture depend on the motion, not only on the current
    target: a solver that sees one frame cannot know it (the input-length ablation).
    """
    rel = np.asarray(target, dtype=float) - SHOULDER
    r = np.hypot(rel[..., 0], rel[..., 1])
    h = rel[..., 2]
    d = np.sqrt(r * r + h * h) / REACH
    w = smootherstep((d - D_NEAR) / (D_FAR - D_NEAR))
    near = PHI_DOWN - K_HEIGHT * h / REACH
    if velocity is not None:
        near = near + K_LEAD * np.tanh(-np.asarray(velocity, dtype=float)[..., 2] / V_LEAD)
    return (1.0 - w) * near - w * np.arctan2(h, r)


def path_velocity(points: np.ndarray) -> np.ndarray:
    """Velocity (n, 3) m/s of a 100 Hz path (n, 3) by central differences (one-sided at the ends)."""
    points = np.asarray(points, dtype=float)
    return np.gradient(points, DT, axis=0) if len(points) > 1 else np.zeros_like(points)


def _rule_ik(points: np.ndarray, velocity: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed form with the posture rule, elbow up: (q (..., 4), reachable (...))."""
    return armkin.ik_closed(points, posture_pitch(points, velocity), True)


def in_workspace(points: np.ndarray) -> np.ndarray:
    """True where a point (..., 3) is in the demonstration workspace (see the module docstring): inside
    the reach, height and axis bounds, and the rule's elbow-up pose within the joint limits by
    `LIMIT_MARGIN` with the elbow bent by at least `DELTA_MIN`. (The margin on joint1, ±π, leaves out a
    0.05 rad wedge straight behind the base.)"""
    points = np.asarray(points, dtype=float)
    rel = points - SHOULDER
    r = np.hypot(rel[..., 0], rel[..., 1])
    geo = (np.linalg.norm(rel, axis=-1) <= D_MAX * REACH) & (r >= R_MIN) & (points[..., 2] >= Z_MIN)
    q, ok = _rule_ik(points)
    inside = np.all((q >= armkin.LOWER + LIMIT_MARGIN) & (q <= armkin.UPPER - LIMIT_MARGIN), axis=-1)
    bent = q[..., 2] + armkin.HALF_PI - armkin.BETA >= DELTA_MIN
    return geo & ok & inside & bent


def demo_joints(points: np.ndarray) -> np.ndarray:
    """Demonstrated joint angles q (n, 4) for a 100 Hz path of tool points (n, 3): `posture_pitch` with
    the path's velocity (`path_velocity`), elbow up, closed form.

    Raises TrajectoryError naming the first frame whose target has no such pose within the joint limits.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise TrajectoryError(f"demo_joints needs points of shape (n, 3), got {points.shape}")
    vel = path_velocity(points)
    q, ok = _rule_ik(points, vel)
    good = ok & armkin.within_limits(q) & np.all(np.isfinite(points), axis=-1)
    if not good.all():
        i = int(np.argmin(good))
        x, y, z = points[i]
        raise TrajectoryError(f"frame {i}: target ({x:.4f}, {y:.4f}, {z:.4f}) m has no elbow-up pose within the "
                              f"joint limits at the demonstrator's pitch "
                              f"{float(posture_pitch(points[i], vel[i])):.3f} rad")
    return q
