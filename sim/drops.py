"""Drop tests: the drops file format, random drops, and the ground truth of a landing (`LandingJudge`).

A drops file is a JSON list of objects, all four fields required::

    {"roll_deg": ±360, "pitch_deg": ±360, "yaw_deg": ±360, "height_m": (0, 20]}

Each drop releases the cat at rest, turned by roll, pitch, yaw (R = Rz(yaw)·Ry(pitch)·Rx(roll)), with its
lowest point ``height_m`` above the floor (`felis.sim.scenarios.drop`).

*Landed* (issue 5, in its words): only the feet touch the ground through touchdown and for
``WINDOW_S`` = 0.5 s after it (touchdown = the first contact of any robot geom with the floor), and
0.5 s after touchdown the upper body's up-axis is within ``TILT_DEG`` = 30° of vertical and the waist
(``State.height``, the ``waist`` site) is above half its standing height (the waist height of the cat at
rest in its ``stand`` pose on the floor, measured from the model: `standing_waist_height`). `landed` is
the pure rule; `LandingJudge` measures its inputs at the physics rate.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np

from felis.errors import ParameterError
from felis.files import check_fields, finite_number
from felis.sim.landing import ImpactRecorder
from felis.sim.robot import MujocoRobot
from felis.sim.scenarios import MAX_DROP_HEIGHT

WINDOW_S = 0.5  # feet only from touchdown to touchdown + WINDOW_S; pose judged at its end
TILT_DEG = 30.0  # up-axis within this of vertical at touchdown + WINDOW_S
WAIST_FRACTION = 0.5  # waist above this fraction of its standing height at touchdown + WINDOW_S
MAX_ANGLE_DEG = 360.0
_FIELDS = ("roll_deg", "pitch_deg", "yaw_deg", "height_m")


@dataclass(frozen=True)
class Drop:
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    height_m: float

    def as_dict(self) -> dict:
        return {k: round(v, 4) for k, v in asdict(self).items()}


def check_drop(item: object, where: str = "drop") -> Drop:
    """One drop from a JSON object; ParameterError naming ``where`` and the field on any fault."""
    check_fields(item, _FIELDS, where, ParameterError)
    nums = {k: finite_number(item, k, where, ParameterError) for k in _FIELDS}
    for k in _FIELDS[:3]:
        if abs(nums[k]) > MAX_ANGLE_DEG:
            raise ParameterError(f"{where}: {k} must be within ±{MAX_ANGLE_DEG:g} degrees, got {nums[k]:g}")
    if not 0.0 < nums["height_m"] <= MAX_DROP_HEIGHT:
        raise ParameterError(f"{where}: height_m must be above 0 and at most {MAX_DROP_HEIGHT:g} m, "
                             f"got {nums['height_m']:g}")
    return Drop(**nums)


def load_drops(path: str | Path) -> list[Drop]:
    """Read a drops file; one-line ParameterError naming the file (and item, and field) on any fault."""
    from felis.files import read_json

    path = Path(path)
    doc = read_json(path, "drops file", ParameterError)
    if not isinstance(doc, list) or not doc:
        raise ParameterError(f"{path}: expected a non-empty JSON list of drops {{{', '.join(_FIELDS)}}}")
    return [check_drop(item, f"{path}: drop {i}") for i, item in enumerate(doc)]


def random_drops(n: int, seed: int = 0, heights: float | tuple[float, ...] = (1.0,)) -> list[Drop]:
    """``n`` drops with roll, pitch and yaw uniform over the full circle [-180, 180) degrees and the
    height taken from ``heights`` in turn (or a fixed value). Deterministic per seed."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ParameterError(f"random:N needs a whole number N ≥ 1, got {n!r}")
    hs = (heights,) if isinstance(heights, int | float) else tuple(heights)
    if not hs:
        raise ParameterError("random drops need at least one height")
    for h in hs:
        if isinstance(h, bool) or not isinstance(h, int | float) or not math.isfinite(h) \
                or not 0.0 < h <= MAX_DROP_HEIGHT:
            raise ParameterError(f"drop height must be above 0 and at most {MAX_DROP_HEIGHT:g} m, got {h!r}")
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-180.0, 180.0, size=(n, 3))
    return [Drop(float(r), float(p), float(y), float(hs[i % len(hs)])) for i, (r, p, y) in enumerate(angles)]


def drops_from(arg: str, seed: int = 0, height: float | None = None) -> list[Drop]:
    """``FILE`` or ``random:N`` (the CLI's --drops); ``height`` (m, default 1.0) is for random:N only."""
    if arg.startswith("random:"):
        try:
            n = int(arg.split(":", 1)[1])
        except ValueError:
            raise ParameterError(f"--drops {arg!r}: expected random:N with N a whole number") from None
        return random_drops(n, seed, 1.0 if height is None else height)
    if height is not None:
        raise ParameterError("--height is for --drops random:N; a drops file gives each drop's height_m")
    return load_drops(arg)


# ------------------------------------------------------------------------------------- ground truth
def landed(foot_only: bool, tilt_deg: float, waist_m: float, standing_waist_m: float) -> bool:
    """The landing rule (module doc): feet only through the window, and at its end tilt ≤ 30° and waist
    > half the standing waist height. NaN inputs never land."""
    return bool(foot_only) and tilt_deg <= TILT_DEG and waist_m > WAIST_FRACTION * standing_waist_m


def tilt_deg(robot: MujocoRobot) -> float:
    """Angle (degrees) between the upper body's (root body's) up-axis and world up."""
    z = float(robot.data.xmat[robot.root_body, 8])
    return math.degrees(math.acos(max(-1.0, min(1.0, z))))


def standing_waist_height(robot: MujocoRobot, settle_s: float = 1.5) -> float:
    """Waist (``State.height``) of the cat at rest in its ``stand`` pose on the floor (m).

    Resets the robot, poses it, sets it down with its feet 1 mm up and lets it settle under the
    ``stand`` controller for ``settle_s``; leaves the robot armed, ready for `MujocoRobot.reset`.
    """
    from felis.controllers import make_controller
    from felis.loop import run_loop
    from felis.sim.scenarios import drop, set_pose

    robot.reset()
    set_pose(robot, robot.spec.pose("stand"))
    drop(robot, 0.001)
    report = run_loop(robot, make_controller("stand"), duration=settle_s, keep_armed=True).raise_if_interrupted()
    height = report.final_state.height if report.final_state is not None else None
    if height is None:
        raise ParameterError(f"{robot.spec.name} has no waist height sensor (sensors.height)")
    return float(height)


class LandingJudge:
    """Physics sub-step hook (``MujocoRobot.substep_hook``) measuring the `landed` rule's inputs at 1 kHz.

    Records touchdown (the first step with any robot–floor contact), any floor contact by a geom that is
    not on a foot body (``feet``: `RobotSpec.sensors.contacts`) from touchdown to touchdown + 0.5 s, and
    the tilt and waist height at touchdown + 0.5 s. It runs an `ImpactRecorder` in the same hook (the
    robot holds one hook) for the peak ground reaction force.
    """

    def __init__(self, robot: MujocoRobot, feet: tuple[str, ...], standing_waist_m: float, floor: str = "floor"):
        m = robot.model
        self.robot = robot
        self.impact = ImpactRecorder(robot, floor)
        self.floor = self.impact.floor
        foot_ids = {robot.body_id(f) for f in feet}
        self.foot_geom = np.array([m.geom_bodyid[g] in foot_ids for g in range(m.ngeom)])
        site = robot.spec.sensors.height
        self.waist_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site) if site else -1
        if self.waist_site < 0:
            raise ParameterError(f"{robot.spec.name} has no waist height site (sensors.height)")
        self.standing_waist_m = float(standing_waist_m)
        self.touchdown_t: float | None = None  # sim time of the first floor contact
        self.first_body: str | None = None  # a body that made it
        self.touch_body: str | None = None  # first non-foot body on the floor within the window
        self.touch_t: float | None = None  # … when (sim time)
        self.tilt_deg: float | None = None  # at touchdown + WINDOW_S
        self.waist_m: float | None = None  # at touchdown + WINDOW_S
        self._end: float | None = None

    def __call__(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        self.impact(m, d)
        if self._end is not None and self.tilt_deg is not None:
            return  # the window is over: nothing more to judge
        t = float(d.time)
        if d.ncon:
            g1, g2 = d.contact.geom1, d.contact.geom2
            on_floor = (g1 == self.floor) | (g2 == self.floor)
            if on_floor.any():
                other = np.where(g1 == self.floor, g2, g1)[on_floor]
                if self.touchdown_t is None:
                    self.touchdown_t, self._end = t, t + WINDOW_S
                    self.first_body = m.body(int(m.geom_bodyid[other[0]])).name
                if self.touch_body is None and t <= self._end + 1e-9:
                    bad = other[~self.foot_geom[other]]
                    if bad.size:
                        self.touch_body = m.body(int(m.geom_bodyid[bad[0]])).name
                        self.touch_t = t
        if self._end is not None and self.tilt_deg is None and t >= self._end - 1e-9:
            self.tilt_deg = tilt_deg(self.robot)
            self.waist_m = float(d.site_xpos[self.waist_site, 2])

    def attach(self) -> LandingJudge:
        self.robot.substep_hook = self
        return self

    def detach(self) -> None:
        if self.robot.substep_hook is self:
            self.robot.substep_hook = None

    @property
    def foot_only(self) -> bool:
        """Feet only from touchdown through the window (False before a touchdown)."""
        return self.touchdown_t is not None and self.touch_body is None

    @property
    def landed(self) -> bool:
        if self.tilt_deg is None or self.waist_m is None:
            return False
        return landed(self.foot_only, self.tilt_deg, self.waist_m, self.standing_waist_m)

    def reasons(self) -> list[tuple[str, str]]:
        """Why it did not land: (kind, detail) pairs, kinds fit for counting; [] when it landed."""
        if self.touchdown_t is None:
            return [("never touched down", "never touched down")]
        out = []
        if self.touch_body is not None:
            dt = self.touch_t - self.touchdown_t
            out.append((f"{self.touch_body} touched the ground",
                        f"{self.touch_body} touched the ground {dt:.3f} s after touchdown"))
        if self.tilt_deg is None or self.waist_m is None:
            out.append(("run ended too early", f"run ended before {WINDOW_S:g} s after touchdown"))
            return out
        if not self.tilt_deg <= TILT_DEG:
            out.append((f"tilt > {TILT_DEG:g}°", f"tilt {self.tilt_deg:.0f}° after {WINDOW_S:g} s"))
        if not self.waist_m > WAIST_FRACTION * self.standing_waist_m:
            out.append(("waist < half standing", f"waist {self.waist_m:.3f} m < half standing "
                        f"({WAIST_FRACTION * self.standing_waist_m:.3f} m) after {WINDOW_S:g} s"))
        return out

    @property
    def peak_impact(self) -> float:
        """Peak ground reaction force in body weights."""
        weight = self.robot.mass() * float(np.linalg.norm(self.robot.model.opt.gravity))
        return self.impact.peak_force / weight if weight > 0 else 0.0
