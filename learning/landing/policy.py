"""The landing policy at run time (seed 000 §6.2–6.3): inputs, gene units and behaviours in numpy, the
spine rule, and reading the shipped policy file. What the landing controller imports; evolution
(operators, fitness, ranking, saving) is in `felis.learning.landing.nets`.

Source: ``seeds/000_d27ba58563dbcb8e.txt`` — §5 (gene units), §6.1 (sensors), §6.2 (controller, spine
rule), §6.3 with Table 1 (inputs and outputs of each net).

**Inputs.** IT = (Ss1, Ss2, St1, St2, Sy1, Sy2, Sh, Sl1…Sl8), 15 values (`IT_NAMES`), built by
`normalise_inputs` from the HAL state:

- Ss1, Ss2, St1, St2, Sl1…Sl8: the 12 joint angles in the description's order
  (``spine_pitch, spine_yaw, tail_pitch, tail_yaw, fl_pitch, fl_roll, …, hr_roll``), each ``q / π``.
- Sy1, Sy2: *our reading.* The paper takes "the local y axes of the upper and lower body" (PhysX is
  y-up). We use the upper body's (the IMU's) roll and pitch, R = Rz(yaw)·Ry(pitch)·Rx(roll)
  (`felis.rotations.roll_pitch`): Sy1 = roll / π ∈ [-1, 1], Sy2 = pitch / (π/2) ∈ [-1, 1]. Gravity's x, y
  in the body frame was the other candidate; it is 0 both upright and upside down, so a net could not
  tell the two apart, while roll is ±π upside down (its jump there only picks a turning direction, both
  of which right the cat).
- Sh: height of the waist above the ground (``State.height``) / `DROP_HEIGHT_M` (3 m, §6.4).

**Nets** (Table 1, `KINDS`). spine: inputs from IT, outputs Vs1, Vs2. tail: inputs from IT + (Vs1, Vs2),
outputs Vt1, Vt2. legs: inputs from IT + (Vs1, Vs2), outputs Vl1…Vl8. compose: inputs from IT, outputs
s1, s2, s3 (dispatch signals for spine, tail, legs). Spine outputs enter the tail and legs nets
normalised (V / max speed, i.e. the spine net's tanh output, in [-1, 1]).

**Gene unit** (§5) ⟨I, O, h, W⟩, with x the net's available inputs::

    y = scale · tanh(W2 · [tanh(W1 · [x_I; 1]); 1]),   W1: h × (|I|+1),  W2: |O| × (h+1)

``scale`` is the max joint speed (rad/s; XL330-M288-T no-load speed ≈ 10.8 rad/s) for the joint nets
and 1 for the compose net. Outputs are joint velocities, which the controller integrates into position
targets; `landing_rule` then holds the spine straight near the ground (§6.2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import ParameterError, PolicyError
from felis.files import read_meta, read_npz
from felis.rotations import roll_pitch, roll_pitch_many
from felis.servos import SERVOS

JOINTS = ("spine_pitch", "spine_yaw", "tail_pitch", "tail_yaw",
          "fl_pitch", "fl_roll", "fr_pitch", "fr_roll",
          "hl_pitch", "hl_roll", "hr_pitch", "hr_roll")  # order of felis/robots/cat.toml
IT_NAMES = ("Ss1", "Ss2", "St1", "St2", "Sy1", "Sy2", "Sh") + tuple(f"Sl{i}" for i in range(1, 9))
N_IT = len(IT_NAMES)  # 15
DROP_HEIGHT_M = 3.0  # §6.4: dropped from 3 m; Sh is normalised by it
MAX_SPEED = SERVOS["XL330-M288-T"].no_load_speed  # rad/s, ≈ 10.79
LANDING_HEIGHT_M = 0.5  # spine held straight below this waist height: eq. 9's 500 mm (our reading)
DEFAULT_POLICY = Path(__file__).parents[1] / "weights" / "landing.npz"  # the shipped policy (`felis train landing`)
FORMAT = "felis-landing-policy"
VERSION = 1


@dataclass(frozen=True)
class NetKind:
    """One row of Table 1: how many inputs the net may choose from, its outputs, the joints it drives
    (indices into `JOINTS`; none for compose) and the default output scale."""

    name: str
    n_available: int
    outputs: tuple[str, ...]
    joints: tuple[int, ...]
    scale: float


KINDS: dict[str, NetKind] = {
    "spine": NetKind("spine", N_IT, ("Vs1", "Vs2"), (0, 1), MAX_SPEED),
    "tail": NetKind("tail", N_IT + 2, ("Vt1", "Vt2"), (2, 3), MAX_SPEED),
    "legs": NetKind("legs", N_IT + 2, tuple(f"Vl{i}" for i in range(1, 9)), tuple(range(4, 12)), MAX_SPEED),
    "compose": NetKind("compose", N_IT, ("s1", "s2", "s3"), (), 1.0),
}
PARTS = ("spine", "tail", "legs")


def _kind(name: str) -> NetKind:
    if name not in KINDS:
        raise ParameterError(f"unknown net kind {name!r}; kinds: {', '.join(KINDS)}")
    return KINDS[name]


# --------------------------------------------------------------------------------------------- inputs


def normalise_inputs(q: Sequence[float] | np.ndarray, quat: Sequence[float] | np.ndarray,
                     height: float) -> np.ndarray:
    """IT (15,) from joint angles ``q`` (12, rad, description order), the upper body's orientation
    ``quat`` (w, x, y, z; ``State.imu.quat``) and the waist height (m; ``State.height``):
    (q_spine, q_tail) / π, roll / π, pitch / (π/2), height / 3 m, q_legs / π."""
    q = np.asarray(q, dtype=float)
    if q.shape != (len(JOINTS),):
        raise ParameterError(f"joint angles have shape {q.shape}, the cat has {len(JOINTS)} joints")
    if not (np.all(np.isfinite(q)) and math.isfinite(height)):
        raise ParameterError("joint angles or height are not finite")
    try:
        roll, pitch = roll_pitch(quat)
    except ValueError as e:  # a zero or non-finite quaternion: the same message, as a ParameterError
        raise ParameterError(str(e)) from None
    it = np.empty(N_IT)
    it[0:4] = q[0:4] / math.pi
    it[4] = roll / math.pi
    it[5] = pitch / (math.pi / 2)
    it[6] = height / DROP_HEIGHT_M
    it[7:15] = q[4:12] / math.pi
    return it


def normalise_inputs_many(q: np.ndarray, quat: np.ndarray, height: np.ndarray) -> np.ndarray:
    """`normalise_inputs` for a batch of cats: q (B, 12), quat (B, 4), height (B,) → IT (B, 15)."""
    q = np.asarray(q, dtype=float)
    roll, pitch = roll_pitch_many(quat)
    it = np.empty((q.shape[0], N_IT))
    it[:, 0:4] = q[:, 0:4] / math.pi
    it[:, 4] = roll / math.pi
    it[:, 5] = pitch / (math.pi / 2)
    it[:, 6] = np.asarray(height, dtype=float) / DROP_HEIGHT_M
    it[:, 7:15] = q[:, 4:12] / math.pi
    return it


def landing_rule(h: float, q_spine_targets: Sequence[float] | np.ndarray) -> np.ndarray:
    """The rule-based module of §6.2: below `LANDING_HEIGHT_M` (waist height ``h`` in m) the spine
    targets become Ss1 = Ss2 = 0 (straight back); above it they pass unchanged. Returns a new array.
    The paper gives no threshold; we use eq. 9's 500 mm, where the scored landing phase begins."""
    t = np.array(q_spine_targets, dtype=float)
    if t.shape != (2,):
        raise ParameterError(f"spine targets have shape {t.shape}, expected (2,)")
    if h < LANDING_HEIGHT_M:
        t[:] = 0.0
    return t


# ------------------------------------------------------------------------------------------ gene unit


@dataclass(frozen=True, eq=False)
class GeneUnit:
    """Gene unit ⟨I, O, h, W⟩ of §5: one net of kind ``kind`` (Table 1).

    ``inputs``: sorted distinct indices into the kind's available inputs (IT, then Vs1, Vs2 for tail and
    legs); ``hidden``: h ≥ 1; ``W1``: h × (|I|+1), last column the bias; ``W2``: |O| × (h+1), last column
    the bias; ``scale``: output scale (rad/s for joint nets). O is fixed by the kind (`outputs`).
    Forward: y = scale · tanh(W2 · [tanh(W1 · [x_I; 1]); 1]). Units are values (W1, W2 read-only): operators
    return new ones.
    """

    kind: str
    inputs: tuple[int, ...]
    hidden: int
    W1: np.ndarray
    W2: np.ndarray
    scale: float
    _fast: tuple | None = field(init=False, repr=False, default=None)

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "inputs", tuple(int(i) for i in self.inputs))
        for name in ("W1", "W2"):
            w = np.array(getattr(self, name), dtype=float)
            w.flags.writeable = False  # a unit is a value; the forward caches below rely on it
            set_(self, name, w)
        set_(self, "scale", float(self.scale))

    @property
    def outputs(self) -> tuple[str, ...]:
        return _kind(self.kind).outputs

    def check(self) -> GeneUnit:
        """PolicyError (one line) unless the kind is known, the inputs are sorted, distinct, in range and
        not empty, h ≥ 1, the weight shapes follow from (I, O, h), and weights and scale are finite
        (scale > 0). Returns the unit."""
        if self.kind not in KINDS:
            raise PolicyError(f"gene unit has unknown kind {self.kind!r}; kinds: {', '.join(KINDS)}")
        k = KINDS[self.kind]
        ins = self.inputs
        if not ins:
            raise PolicyError(f"{self.kind} unit has no inputs")
        if any(b <= a for a, b in zip(ins, ins[1:], strict=False)):
            raise PolicyError(f"{self.kind} unit inputs {ins} are not sorted and distinct")
        if ins[0] < 0 or ins[-1] >= k.n_available:
            raise PolicyError(f"{self.kind} unit inputs {ins} out of range 0..{k.n_available - 1}")
        if self.hidden < 1:
            raise PolicyError(f"{self.kind} unit has {self.hidden} hidden neurons; needs at least 1")
        if self.W1.shape != (self.hidden, len(ins) + 1):
            raise PolicyError(f"{self.kind} unit W1 has shape {self.W1.shape}, expected "
                              f"{(self.hidden, len(ins) + 1)} (hidden × inputs+1)")
        if self.W2.shape != (len(k.outputs), self.hidden + 1):
            raise PolicyError(f"{self.kind} unit W2 has shape {self.W2.shape}, expected "
                              f"{(len(k.outputs), self.hidden + 1)} (outputs × hidden+1)")
        if not (np.all(np.isfinite(self.W1)) and np.all(np.isfinite(self.W2))):
            raise PolicyError(f"{self.kind} unit holds non-finite weights")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise PolicyError(f"{self.kind} unit has output scale {self.scale}; needs a finite value > 0")
        return self

    def _weights(self) -> tuple:
        """W1 spread over all available inputs (zeros where not in I), biases apart; built once."""
        if self._fast is None:
            a = np.zeros((self.hidden, _kind(self.kind).n_available))
            a[:, list(self.inputs)] = self.W1[:, :-1]
            object.__setattr__(self, "_fast", (a, self.W1[:, -1].copy(), np.ascontiguousarray(self.W2[:, :-1]),
                                               self.W2[:, -1].copy()))
        return self._fast

    def raw(self, x: np.ndarray) -> np.ndarray:
        """tanh(W2 · [tanh(W1 · [x_I; 1]); 1]) ∈ (-1, 1)^|O| for the available inputs ``x``."""
        a, b1, c, b2 = self._weights()
        return np.tanh(c @ np.tanh(a @ x + b1) + b2)

    def raw_many(self, x: np.ndarray) -> np.ndarray:
        """`raw` for a batch: ``x`` (B, available inputs) → (B, |O|)."""
        a, b1, c, b2 = self._weights()
        return np.tanh(np.tanh(x @ a.T + b1) @ c.T + b2)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """scale · `raw`: joint velocities (rad/s) or, for compose, dispatch signals in (-1, 1)."""
        return self.scale * self.raw(x)

    def copy(self) -> GeneUnit:
        return GeneUnit(self.kind, self.inputs, self.hidden, self.W1.copy(), self.W2.copy(), self.scale)


# -------------------------------------------------------------------------------------- behaviours


def _check_it(it: np.ndarray) -> np.ndarray:
    if it.shape != (N_IT,):
        raise ParameterError(f"IT has shape {it.shape}, expected ({N_IT},)")
    return it


@dataclass(frozen=True, eq=False)
class SimpleBehaviour:
    """A simple behaviour (§6.2–6.3): spine, tail and legs units; one per training orientation."""

    spine: GeneUnit
    tail: GeneUnit
    legs: GeneUnit

    def check(self) -> SimpleBehaviour:
        for part in PARTS:
            unit = getattr(self, part)
            if unit.kind != part:
                raise PolicyError(f"simple behaviour's {part} unit is of kind {unit.kind!r}")
            unit.check()
        return self

    def velocities(self, it: np.ndarray) -> np.ndarray:
        """(12,) joint velocities (rad/s, `JOINTS` order) for IT (15,): spine from IT, tail and legs from
        IT + the spine net's normalised outputs."""
        return _drive(self.spine, self.tail, self.legs, _check_it(it))

    def velocities_many(self, it: np.ndarray) -> np.ndarray:
        """`velocities` for a batch: IT (B, 15) → (B, 12)."""
        return _drive_many(self.spine, self.tail, self.legs, it)


def _drive_many(spine: GeneUnit, tail: GeneUnit, legs: GeneUnit, it: np.ndarray) -> np.ndarray:
    s = spine.raw_many(it)
    x = np.concatenate((it, s), axis=1)
    return np.concatenate((spine.scale * s, tail.scale * tail.raw_many(x), legs.scale * legs.raw_many(x)), axis=1)


class StackedSimple:
    """Many simple behaviours evaluated for a batch of cats in one go (`felis.controllers.landing.LandingBatch`
    with a population): each part's units are padded to the largest hidden layer with zero weights (a zero
    hidden neuron adds tanh(0)·0 = 0) and stacked, then gathered per row, so a tick is six `numpy.einsum`s
    whatever the number of behaviours. ``index[b]``: the behaviour of row b."""

    def __init__(self, behaviours: Sequence[SimpleBehaviour], index: np.ndarray):
        index = np.asarray(index, dtype=int)
        self.parts = []
        for part in PARTS:
            units = [getattr(b, part) for b in behaviours]
            n_in = _kind(part).n_available
            h = max(u.hidden for u in units)
            n_out = len(_kind(part).outputs)
            A, b1 = np.zeros((len(units), h, n_in)), np.zeros((len(units), h))
            C, b2 = np.zeros((len(units), n_out, h)), np.zeros((len(units), n_out))
            scale = np.array([u.scale for u in units])
            for i, u in enumerate(units):
                a, c1, c, c2 = u._weights()
                A[i, :u.hidden], b1[i, :u.hidden], C[i, :, :u.hidden], b2[i] = a, c1, c, c2
            self.parts.append((A[index], b1[index], C[index], b2[index], scale[index][:, None]))

    def velocities_many(self, it: np.ndarray) -> np.ndarray:
        """(B, 12) joint velocities for IT (B, 15), row b by behaviour ``index[b]``."""
        def raw(p, x):
            A, b1, C, b2, _ = p
            return np.tanh(np.einsum("boh,bh->bo", C, np.tanh(np.einsum("bhn,bn->bh", A, x) + b1)) + b2)

        sp, tl, lg = self.parts
        s = raw(sp, it)
        x = np.concatenate((it, s), axis=1)
        return np.concatenate((sp[4] * s, tl[4] * raw(tl, x), lg[4] * raw(lg, x)), axis=1)


def _drive(spine: GeneUnit, tail: GeneUnit, legs: GeneUnit, it: np.ndarray) -> np.ndarray:
    s = spine.raw(it)
    x = np.concatenate((it, s))
    return np.concatenate((spine.scale * s, tail.scale * tail.raw(x), legs.scale * legs.raw(x)))


def dispatch_index(s: np.ndarray | float, k: int) -> np.ndarray:
    """Dispatch signal s ∈ [-1, 1] → behaviour index clip(floor((s + 1)/2 · K), 0, K−1): K equal bins."""
    return np.clip(np.floor((np.asarray(s) + 1.0) * 0.5 * k), 0, k - 1).astype(int)


@dataclass(frozen=True, eq=False)
class ComplexBehaviour:
    """A complex behaviour (eq. 1, §6.2): K simple behaviours and a compose unit whose outputs s1, s2, s3
    choose, per part (spine, tail, legs), which simple behaviour's net drives it (`dispatch_index`).
    The tail and legs nets take the outputs of the spine net that was chosen (the spine actually moving)."""

    behaviours: tuple[SimpleBehaviour, ...]
    compose: GeneUnit

    def __post_init__(self):
        object.__setattr__(self, "behaviours", tuple(self.behaviours))

    def check(self) -> ComplexBehaviour:
        if not self.behaviours:
            raise PolicyError("complex behaviour has no simple behaviours")
        for b in self.behaviours:
            b.check()
        if self.compose.kind != "compose":
            raise PolicyError(f"complex behaviour's compose unit is of kind {self.compose.kind!r}")
        self.compose.check()
        return self

    def dispatch(self, it: np.ndarray) -> np.ndarray:
        """(3,) indices of the simple behaviours driving spine, tail, legs for IT."""
        return dispatch_index(self.compose.raw(_check_it(it)), len(self.behaviours))

    def velocities(self, it: np.ndarray) -> np.ndarray:
        """(12,) joint velocities (rad/s, `JOINTS` order) for IT (15,)."""
        i, j, k = self.dispatch(it)
        b = self.behaviours
        return _drive(b[i].spine, b[j].tail, b[k].legs, it)

    def velocities_many(self, it: np.ndarray) -> np.ndarray:
        """`velocities` for a batch: IT (B, 15) → (B, 12); rows are grouped by the behaviours they dispatch to."""
        idx = dispatch_index(self.compose.raw_many(it), len(self.behaviours))  # (B, 3)
        out = np.empty((it.shape[0], len(JOINTS)))
        b = self.behaviours
        keys, inverse = np.unique(idx, axis=0, return_inverse=True)
        for g, (i, j, k) in enumerate(keys):
            rows = np.flatnonzero(inverse.ravel() == g)
            out[rows] = _drive_many(b[i].spine, b[j].tail, b[k].legs, it[rows])
        return out


# -------------------------------------------------------------------------------------- policy files


def _load_unit(path: Path, data: Mapping[str, np.ndarray], units: Mapping[str, Any], name: str,
               kind: str) -> GeneUnit:
    entry = units.get(name)
    if not isinstance(entry, dict):
        raise PolicyError(f"{path}: metadata lacks unit {name!r}")
    if entry.get("kind") != kind:
        raise PolicyError(f"{path}: unit {name!r} is of kind {entry.get('kind')!r}, expected {kind!r}")
    arr = {}
    for a in ("inputs", "W1", "W2"):
        key = f"{name}/{a}"
        if key not in data:
            raise PolicyError(f"{path}: lacks array {key!r}")
        arr[a] = data[key]
    if arr["inputs"].ndim != 1 or arr["inputs"].dtype.kind not in "iu":
        raise PolicyError(f"{path}: array '{name}/inputs' is not a 1-D integer array")
    for a in ("W1", "W2"):
        if arr[a].ndim != 2 or arr[a].dtype.kind != "f":
            raise PolicyError(f"{path}: array '{name}/{a}' is not a 2-D float array")
    hidden, scale = entry.get("hidden"), entry.get("scale")
    if not isinstance(hidden, int) or isinstance(scale, bool) or not isinstance(scale, int | float):
        raise PolicyError(f"{path}: unit {name!r} metadata needs an integer hidden and a number scale")
    unit = GeneUnit(kind, tuple(arr["inputs"].tolist()), hidden, arr["W1"], arr["W2"], scale)
    try:
        return unit.check()
    except PolicyError as e:
        raise PolicyError(f"{path}: unit {name!r}: {e}") from None


def load_policy(path: str | Path) -> tuple[SimpleBehaviour | ComplexBehaviour, dict[str, Any]]:
    """Read a policy written by `save_policy`: (behaviour, the caller's ``meta``). Every fault is one-line
    `PolicyError` naming the file: missing, a directory, not an npz, corrupt or truncated, pickled
    objects, no or bad metadata, another format or version, joints other than the cat's 12, a missing
    unit or array, shapes that do not fit the unit's structure, non-finite weights."""
    path = Path(path)
    data = read_npz(path, "landing policy", PolicyError)
    doc = read_meta(data, path, PolicyError, "landing policy",
                    ident=("format", FORMAT, "format {got!r} is not {want!r}; not a landing policy"),
                    version=("version", VERSION,
                             "policy version {got!r} is not supported (felis reads version {want})"))
    joints = doc.get("joints")
    if not isinstance(joints, list) or len(joints) != len(JOINTS):
        n = len(joints) if isinstance(joints, list) else "no"
        raise PolicyError(f"{path}: policy is for {n} joints, the cat has {len(JOINTS)}")
    if tuple(joints) != JOINTS:
        raise PolicyError(f"{path}: policy joints {joints} are not the cat's {list(JOINTS)}")
    if doc.get("it") != list(IT_NAMES):
        raise PolicyError(f"{path}: policy inputs {doc.get('it')} are not IT {list(IT_NAMES)}")
    units = doc.get("units")
    if not isinstance(units, dict):
        raise PolicyError(f"{path}: metadata lists no units")
    meta = doc.get("meta", {})
    if not isinstance(meta, dict):
        raise PolicyError(f"{path}: 'meta' is not a JSON object")

    def simple(pre: str) -> SimpleBehaviour:
        return SimpleBehaviour(*(_load_unit(path, data, units, pre + p, p) for p in PARTS))

    kind = doc.get("type")
    if kind == "simple":
        return simple(""), meta
    if kind == "complex":
        n_b = doc.get("behaviours")
        if not isinstance(n_b, int) or isinstance(n_b, bool) or n_b < 1:
            raise PolicyError(f"{path}: complex policy has behaviour count {n_b!r}; needs an integer ≥ 1")
        bs = tuple(simple(f"b{i}/") for i in range(n_b))
        return ComplexBehaviour(bs, _load_unit(path, data, units, "compose", "compose")), meta
    raise PolicyError(f"{path}: policy type {kind!r} is neither 'simple' nor 'complex'")
