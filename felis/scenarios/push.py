"""Pushes: the one `Push` type, its validator, the push file format and random pushes.

A push file is a JSON list of objects::

    {"body": "upper_body" | "lower_body", "direction_deg": 0 = +x, counter-clockwise,
     "impulse_ns": N·s (> 0), "t_s": s after the run starts, "phase": "stand" | "step"}

The impulse is horizontal, applied at the body's centre of mass (`felis.sim.scenarios.push`, which
checks any impulse against `MAX_IMPULSE`). A push episode lasts until ``t_s + FALL_WINDOW_S``; whether
the robot fell in it is `felis.scenarios.verdicts.fall_reason`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.files import check_fields, finite_number, read_json_list

BODIES = ("upper_body", "lower_body")
PHASES = ("stand", "step")
MAX_IMPULSE = 50.0  # N·s
FALL_WINDOW_S = 2.0  # a push episode runs this long after the push
MIN_T_S = {"stand": 0.5, "step": 1.5}  # the stance settles / the gait has ramped in by then
MAX_T_S = 30.0
FIELDS = ("body", "direction_deg", "impulse_ns", "t_s", "phase")


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
    check_fields(item, FIELDS, where, ParameterError)
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
    return read_json_list(path, "push file", "pushes", "push", check_push, ParameterError)


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
