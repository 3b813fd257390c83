"""Push tests: the push file format, random pushes, and the scenario monitors that run them (`Pusher`
and `FallDetector` on a model the loop steps; `ThreadedPushTest` on the virtual bus's model, which
another thread steps).

A push file is a JSON list of objects::

    {"body": "upper_body" | "lower_body", "direction_deg": 0 = +x, counter-clockwise,
     "impulse_ns": N·s (> 0), "t_s": s after the run starts, "phase": "stand" | "step"}

The impulse is horizontal, applied at the body's centre of mass (`felis.sim.scenarios.push`).
Ground truth (`FallDetector`): the robot *fell* when, within `FALL_WINDOW_S` of the push, any body
other than the feet touches the ground or the upper body tilts past `FALL_TILT_DEG`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np

from felis.errors import ParameterError
from felis.files import check_fields, finite_number
from felis.sim.robot import MujocoRobot
from felis.sim.scenarios import MAX_IMPULSE, push

BODIES = ("upper_body", "lower_body")
PHASES = ("stand", "step")
FALL_WINDOW_S = 2.0
FALL_TILT_DEG = 60.0
MIN_T_S = {"stand": 0.5, "step": 1.5}  # the stance settles / the gait has ramped in by then
MAX_T_S = 30.0
_FIELDS = ("body", "direction_deg", "impulse_ns", "t_s", "phase")


@dataclass(frozen=True)
class Push:
    body: str
    direction_deg: float
    impulse_ns: float
    t_s: float
    phase: str

    def impulse(self) -> np.ndarray:
        a = math.radians(self.direction_deg)
        return np.array([math.cos(a), math.sin(a), 0.0]) * self.impulse_ns

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def check_push(item: object, where: str = "push") -> Push:
    """One push from a JSON object; ParameterError naming ``where`` and the field on any fault."""
    check_fields(item, _FIELDS, where, ParameterError)
    body, phase = item["body"], item["phase"]
    if body not in BODIES:
        raise ParameterError(f"{where}: body {body!r} is not one of {', '.join(BODIES)}")
    if phase not in PHASES:
        raise ParameterError(f"{where}: phase {phase!r} is not one of {', '.join(PHASES)}")
    nums = {k: finite_number(item, k, where, ParameterError) for k in ("direction_deg", "impulse_ns", "t_s")}
    if not 0 < nums["impulse_ns"] <= MAX_IMPULSE:
        raise ParameterError(f"{where}: impulse_ns must be above 0 and at most {MAX_IMPULSE:g} N·s, "
                             f"got {nums['impulse_ns']:g}")
    if not MIN_T_S[phase] <= nums["t_s"] <= MAX_T_S:
        raise ParameterError(f"{where}: t_s must be within {MIN_T_S[phase]:g}…{MAX_T_S:g} s for phase {phase} "
                             f"(the robot settles first), got {nums['t_s']:g}")
    return Push(body, nums["direction_deg"] % 360.0, nums["impulse_ns"], nums["t_s"], phase)


def load_pushes(path: str | Path) -> list[Push]:
    """Read a push file; one-line ParameterError naming the file (and item) on any fault."""
    from felis.files import read_json

    path = Path(path)
    doc = read_json(path, "push file", ParameterError)
    if not isinstance(doc, list) or not doc:
        raise ParameterError(f"{path}: expected a non-empty JSON list of pushes")
    return [check_push(item, f"{path}: push {i}") for i, item in enumerate(doc)]


def random_pushes(n: int, seed: int = 0, impulse: tuple[float, float] = (0.1, 1.2),
                  phases: tuple[str, ...] = PHASES) -> list[Push]:
    """``n`` pushes: body, phase and direction uniform, impulse uniform in ``impulse`` N·s, time
    uniform over one gait cycle after the settle time. Deterministic per seed."""
    if n < 1:
        raise ParameterError(f"random:N needs N ≥ 1, got {n}")
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        phase = phases[int(rng.integers(len(phases)))]
        out.append(Push(body=BODIES[int(rng.integers(2))], direction_deg=float(rng.uniform(0, 360)),
                        impulse_ns=float(rng.uniform(*impulse)),
                        t_s=float(MIN_T_S[phase] + rng.uniform(0, 0.5)), phase=phase))
    return out


def pushes_from(arg: str, seed: int = 0) -> list[Push]:
    """``FILE`` or ``random:N`` (the CLI's --pushes)."""
    if arg.startswith("random:"):
        try:
            n = int(arg.split(":", 1)[1])
        except ValueError:
            raise ParameterError(f"--pushes {arg!r}: expected random:N with N a whole number") from None
        return random_pushes(n, seed)
    return load_pushes(arg)


class Pusher:
    """Loop monitor that applies ``push`` to the simulation once the run's clock reaches ``push.t_s``."""

    def __init__(self, robot: MujocoRobot, p: Push):
        self.robot, self.push = robot, p
        self.t: float | None = None  # when it was applied (run clock)

    def __call__(self, state, command) -> None:
        if self.t is None and state.t >= self.push.t_s - 1e-9:
            push(self.robot, self.push.body, self.push.impulse())
            self.t = state.t


class ThreadedPushTest:
    """The push and the fall detector for a model stepped in another thread (the virtual bus's).

    The loop monitor (``__call__``, in the loop's thread) only asks for the push when its clock reaches
    ``t_s``; the physics thread applies it between two steps and checks for a fall every
    ``check_every`` steps, through ``robot.substep_hook``: nothing touches the model mid-step. Times
    are mapped to the loop's clock by the push: t_loop = t_push_loop + (t_sim − t_push_sim).
    """

    def __init__(self, robot: MujocoRobot, p: Push, feet: tuple[str, ...], check_every: int = 5):
        self.robot, self.push, self.check_every = robot, p, check_every
        self.detector = FallDetector(robot, feet)
        self.t: float | None = None  # push, loop clock
        self._asked = False
        self._push_sim: float | None = None
        self._fall_sim: float | None = None
        self._n = 0
        robot.substep_hook = self._substep

    def __call__(self, state, command) -> None:
        if not self._asked and state.t >= self.push.t_s - 1e-9:
            self.t, self._asked = state.t, True

    def _substep(self, m, d) -> None:
        if self._asked and self._push_sim is None:
            push(self.robot, self.push.body, self.push.impulse())
            self._push_sim = float(d.time)
        self._n += 1
        if self._fall_sim is None and self._n % self.check_every == 0:
            why = self.detector.check()
            if why:
                self._fall_sim, self.detector.why = float(d.time), why

    def detach(self) -> None:
        self.robot.substep_hook = None

    @property
    def fall_t(self) -> float | None:
        """Fall time on the loop's clock (None: no fall, or it came before the push was applied)."""
        if self._fall_sim is None or self._push_sim is None or self.t is None:
            return None
        return self.t + (self._fall_sim - self._push_sim)


class FallDetector:
    """Loop monitor: ground truth of a fall (module doc), checked every tick on the simulation."""

    def __init__(self, robot: MujocoRobot, feet: tuple[str, ...], floor: str = "floor"):
        m = robot.model
        self.robot = robot
        self.floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, floor)
        foot_ids = {robot.body_id(f) for f in feet}
        self.foot_geom = np.array([m.geom_bodyid[g] in foot_ids for g in range(m.ngeom)])
        self.root = robot.root_body
        self.t: float | None = None  # first tick that met the fall condition (run clock)
        self.why = ""
        self.max_tilt_deg = 0.0

    def check(self) -> str:
        """'' while standing, else why it counts as fallen now."""
        m, d = self.robot.model, self.robot.data
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(d.xmat[self.root, 8])))))
        self.max_tilt_deg = max(self.max_tilt_deg, tilt)
        for i in range(d.ncon):
            c = d.contact[i]
            other = c.geom2 if c.geom1 == self.floor else c.geom1 if c.geom2 == self.floor else -1
            if other >= 0 and not self.foot_geom[other]:
                return f"{m.body(int(m.geom_bodyid[other])).name} touched the ground"
        if tilt > FALL_TILT_DEG:
            return f"upper body tilted {tilt:.0f}°"
        return ""

    def __call__(self, state, command) -> None:
        if self.t is None:
            why = self.check()
            if why:
                self.t, self.why = state.t, why
