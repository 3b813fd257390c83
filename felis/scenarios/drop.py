"""Drops: the one `Drop` type, its one validator, the drops file format and random drops.

A drop releases the robot at rest, turned by roll, pitch, yaw (degrees, R = Rz(yaw)·Ry(pitch)·Rx(roll),
x forward, y left, z up), with its lowest point ``height_m`` above the floor; free fall to the first
contact then takes t = √(2h/g). `felis.sim.scenarios.apply_drop` puts a simulated robot there; the
virtual bus holds it there until torque comes on (`felis.sim.servo_in_loop`).

Limits (`check_limits`, the one place they are checked): 0 < height ≤ `MAX_DROP_HEIGHT` m, each angle
within ±`MAX_ANGLE_DEG`. Three front doors read a drop and share it — `make_drop` (numbers: the CLI and
the simulation), `drop_from_values` (a 4-sequence height, roll, pitch, yaw: the virtual bus) and
`check_drop` (a JSON object: drops files) — each with the one-line error its input calls for.

A drops file is a JSON list of objects, all four fields required::

    {"roll_deg": ±360, "pitch_deg": ±360, "yaw_deg": ±360, "height_m": (0, 20]}
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.files import check_fields, finite_number, read_json_list
from felis.rotations import G

MAX_DROP_HEIGHT = 20.0  # m
MAX_ANGLE_DEG = 360.0
FIELDS = ("roll_deg", "pitch_deg", "yaw_deg", "height_m")


@dataclass(frozen=True)
class Drop:
    """One drop (module doc): orientation in degrees, height of the lowest point in metres."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    height_m: float

    @property
    def fall_time(self) -> float:
        """Free fall to the first contact (s): √(2h/g), g = `felis.rotations.G` (the models' gravity)."""
        return math.sqrt(2 * self.height_m / G)

    # The names the run summaries (`felis sim drop`, the virtual bus) print a drop with.
    height = property(lambda self: self.height_m, doc="height_m")
    roll = property(lambda self: self.roll_deg, doc="roll_deg")
    pitch = property(lambda self: self.pitch_deg, doc="pitch_deg")
    yaw = property(lambda self: self.yaw_deg, doc="yaw_deg")

    def as_dict(self) -> dict:
        return {k: round(v, 4) for k, v in asdict(self).items()}


def check_limits(values: dict[str, float], prefix: str) -> None:
    """The drop's limits (module doc), checked in the order of ``values`` (name → finite number; a name
    starting with ``height`` is the height, any other an angle); ParameterError ``<prefix><name> …``."""
    for name, v in values.items():
        if name.startswith("height"):
            if not 0.0 < v <= MAX_DROP_HEIGHT:
                raise ParameterError(f"{prefix}{name} must be above 0 and at most {MAX_DROP_HEIGHT:g} m, got {v:g}")
        elif abs(v) > MAX_ANGLE_DEG:
            raise ParameterError(f"{prefix}{name} must be within ±{MAX_ANGLE_DEG:g} degrees, got {v:g}")


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ParameterError(f"{name} must be finite, got {value}")
    return v


def make_drop(height: float, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> Drop:
    """A drop from numbers (height m, roll°, pitch°, yaw°); one-line ParameterError ("drop height must be …")."""
    h = _finite("height", height)
    r, p, y = (_finite(n, a) for n, a in (("roll", roll), ("pitch", pitch), ("yaw", yaw)))
    check_limits({"height": h, "roll": r, "pitch": p, "yaw": y}, "drop ")
    return Drop(r, p, y, h)


def drop_from_values(values: Sequence[float]) -> Drop:
    """A drop from four numbers (height m, roll°, pitch°, yaw°), as the virtual bus takes it."""
    try:
        nums = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        nums = ()
    if len(nums) != 4 or not all(math.isfinite(v) for v in nums):
        raise ParameterError(f"a drop is four finite numbers: height (m), roll, pitch, yaw (degrees), got {values!r}")
    h, r, p, y = nums
    check_limits({"height": h, "roll": r, "pitch": p, "yaw": y}, "drop ")
    return Drop(r, p, y, h)


def check_drop(item: object, where: str = "drop") -> Drop:
    """One drop from a JSON object; ParameterError naming ``where`` and the field on any fault."""
    check_fields(item, FIELDS, where, ParameterError)
    nums = {k: finite_number(item, k, where, ParameterError) for k in FIELDS}
    check_limits(nums, f"{where}: ")
    return Drop(**nums)


def load_drops(path: str | Path) -> list[Drop]:
    """Read a drops file; one-line ParameterError naming the file (and item, and field) on any fault."""
    return read_json_list(path, "drops file", f"drops {{{', '.join(FIELDS)}}}", "drop", check_drop, ParameterError)


def _heights(n: int, heights: float | tuple[float, ...]) -> tuple[float, ...]:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ParameterError(f"random:N needs a whole number N ≥ 1, got {n!r}")
    hs = (heights,) if isinstance(heights, int | float) else tuple(heights)
    if not hs:
        raise ParameterError("random drops need at least one height")
    for h in hs:
        if isinstance(h, bool) or not isinstance(h, int | float) or not math.isfinite(h) \
                or not 0.0 < h <= MAX_DROP_HEIGHT:
            raise ParameterError(f"drop height must be above 0 and at most {MAX_DROP_HEIGHT:g} m, got {h!r}")
    return hs


def random_drops(n: int, seed: int = 0, heights: float | tuple[float, ...] = (1.0,)) -> list[Drop]:
    """``n`` drops in orientations drawn uniformly over all rotations (Haar measure: what "a random
    orientation" means; `scipy.spatial.transform.Rotation.random`), given as roll, pitch, yaw in degrees
    (R = Rz(yaw)·Ry(pitch)·Rx(roll)), the height taken from ``heights`` in turn (or a fixed value).
    Deterministic per seed. The start tilt θ (up-axis from vertical) then has P(tilt ≤ θ) = (1 − cos θ)/2:
    half the drops start tilted more than 90°. `euler_drops` is the older draw (each angle uniform)."""
    from scipy.spatial.transform import Rotation

    hs = _heights(n, heights)
    ypr = Rotation.random(n, random_state=np.random.default_rng(seed)).as_euler("ZYX", degrees=True)
    return [Drop(float(r), float(p), float(y), float(hs[i % len(hs)])) for i, (y, p, r) in enumerate(ypr)]


def euler_drops(n: int, seed: int = 0, heights: float | tuple[float, ...] = (1.0,)) -> list[Drop]:
    """``n`` drops with roll, pitch and yaw each uniform in [-180, 180) degrees (``euler:N``; felis's
    ``random:N`` before issue 21: it puts more drops near upright than a uniform rotation does).
    Deterministic per seed."""
    hs = _heights(n, heights)
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-180.0, 180.0, size=(n, 3))
    return [Drop(float(r), float(p), float(y), float(hs[i % len(hs)])) for i, (r, p, y) in enumerate(angles)]


def drops_from(arg: str, seed: int = 0, height: float | None = None) -> list[Drop]:
    """``FILE``, ``random:N`` (uniform rotations) or ``euler:N`` (uniform Euler angles) — the CLI's --drops;
    ``height`` (m, default 1.0) is for the random draws only."""
    for prefix, draw in (("random:", random_drops), ("euler:", euler_drops)):
        if arg.startswith(prefix):
            try:
                n = int(arg.split(":", 1)[1])
            except ValueError:
                raise ParameterError(f"--drops {arg!r}: expected {prefix}N with N a whole number") from None
            return draw(n, seed, 1.0 if height is None else height)
    if height is not None:
        raise ParameterError("--height is for --drops random:N or euler:N; a drops file gives each drop's height_m")
    return load_drops(arg)
