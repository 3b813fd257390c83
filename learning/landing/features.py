"""Motion features and motion similarity for the falling cat's imitation learning.

Source: seed 000 (``000_d27ba58563dbcb8e.txt``) §3 (feature extraction) and §4 (similarity); summary in
``shared/reference/methods.md``, "Evolved landing nets by imitation learning". A motion is a sequence of
frames (100 Hz; a drop is 200 of them); a rollout that imitates a motion sample is ranked by how close
its features come to the sample's.

Segment vectors (the paper's r_n, "direction of node n relative to its parent"). For each body j of
`FEATURE_BODIES` a vector r_j from a point of its parent side to a point of j, in world coordinates,
then expressed in the *heading frame*: z is world up (a falling cat's "above" is about gravity), x the
root body's forward axis projected on the horizontal plane, y = z × x (left). The cat has no knees and
its link origins sit on joint axes, so the literal origin-to-origin vectors of the model would be
constant in the torso frame for the legs, the waist and the tail; the points are chosen so each vector
follows the segment's own joint (`SEGMENTS`):

==========  ====================================  ===========================================
body j      vector                                at rest (all joints 0, cat upright)
==========  ====================================  ===========================================
head        upper_body origin → head origin       (+0.082, 0, −0.003): front, below; rigid on the
                                                  torso, so it tells torso pitch/roll only (front
                                                  is always True in the heading frame)
xx_leg      hip (leg origin) → foot origin        (0, 0, −0.085): straight down
xx_foot     hip (leg origin) → foot origin        same as its leg (no knee: the foot is rigid
                                                  on the leg, so "foot relative to leg" is the
                                                  leg's direction; legs count twice in B, TF)
lower_body  waist (lower_body origin) → its CoM   (−0.062, 0, 0): behind; spine pitch/yaw set
                                                  above/left
tail        tail base (tail origin) → its CoM     (−0.063, 0, 0): behind; along the capsule
==========  ====================================  ===========================================

Logical features (eq. 2–3). b_j = (front, left, above) = (r_x > 0, r_y > 0, r_z > 0) in the heading
frame, strictly, so an exactly zero component reads False (a straight, untilted segment is "not left"
and "not above"); near zero the bit follows the sign of small joint angles. B = (b_1, …, b_J) flattened
body by body, B[t, 3j + k] with k = 0 front, 1 left, 2 above.

Spatio-temporal feature (eq. 3–4). PCA reduces B to L (`Pca`); SF = (L_1, …, L_T).

Probabilistic feature (eq. 5–6). Each b_j is one of 8 states s = 4·front + 2·left + above, i.e. the
paper's row order (0,0,0), (0,0,1), …, (1,1,1). P_j[s, s'] = #{t : s_j(t) = s, s_j(t+1) = s'} / T, the
count of consecutive-frame transitions divided by the total number of frames T, as eq. 6 states it
("the total number divided by the total number of frames"). Row = first frame, column = next frame.
Despite the paper's p(·|·) notation these are joint frequencies, not conditional probabilities: all
entries sum to (T − 1)/T. TF = (P_1, …, P_J), shape (J, 8, 8).

Similarity (§4). D = ½(DTW(SF, SF′) + DTW(SF′, SF)) (eq. 7), with the paper's recurrence::

    DTW[0, 0] = 0,  DTW[i, 0] = DTW[0, j] = ∞   (i, j ≥ 1)
    DTW[i, j] = |L_i − L′_j| + min(DTW[i−1, j], DTW[i, j−1], DTW[i−1, j−1])
    DTW(SF, SF′) = DTW[n, m]

(the paper writes d = |L_i − L′_i|, a typo: the cost must depend on j; and n = m = T_M, here any
lengths). |·| is the Euclidean norm. The paper calls DTW(SF, SF′) "the DTW distance with SF as
reference", but its recurrence is symmetric: the steps (1,0), (0,1), (1,1) all weigh 1 and nothing is
normalised by one sequence's length, so DTW(SF′, SF) is the same number (bit for bit, here) and
D equals either term; `motion_distance` still evaluates eq. 7 as written. S = Σ_j Σ_{s,s'}
|P_j[s, s'] − P′_j[s, s']| (eq. 8, the matrix |·| read as the entrywise 1-norm).

Speed. `dtw` fills the DTW table by anti-diagonals (cells with equal i + j depend only on earlier
diagonals), each diagonal a strided view of the flat table, so it does exactly the reference's
arithmetic in n + m − 1 numpy steps; `dtw_reference` is the plain double loop.
``bench/dtw_speed.py`` times it against a 200-step rollout of the cat.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.distance import cdist

from felis.errors import ParameterError

ROOT_BODY = "upper_body"
FEATURE_BODIES = ("head", "fl_leg", "fl_foot", "fr_leg", "fr_foot", "lower_body",
                  "hl_leg", "hl_foot", "hr_leg", "hr_foot", "tail")
N_STATES = 8

# body j -> ((body, point), (body, point)): the vector r_j runs from the first point to the second;
# point "origin" is the body frame's origin (MjData.xpos), "com" its centre of mass (MjData.xipos).
SEGMENTS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "head": (("upper_body", "origin"), ("head", "origin")),
    **{f"{leg}_{part}": ((f"{leg}_leg", "origin"), (f"{leg}_foot", "origin"))
       for leg in ("fl", "fr", "hl", "hr") for part in ("leg", "foot")},
    "lower_body": (("lower_body", "origin"), ("lower_body", "com")),
    "tail": (("tail", "origin"), ("tail", "com")),
}


# ---------------------------------------------------------------------------------------- recording
@dataclass(frozen=True)
class SegmentIndex:
    """Rows of ``concatenate((d.xpos, d.xipos))`` for each segment's start and end point, and the root body.

    Resolve once per model (`segment_index`) and pass to `body_frame` to skip name look-ups per frame.
    """

    root: int
    start: np.ndarray
    end: np.ndarray


def segment_index(m: mujoco.MjModel) -> SegmentIndex:
    """Look up the bodies of `SEGMENTS` and `ROOT_BODY` in a compiled model (the cat's MJCF)."""
    def body(name: str) -> int:
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise ParameterError(f"motion features need body {name!r}, which the model lacks (is it the cat?)")
        return bid

    def row(point: tuple[str, str]) -> int:
        return body(point[0]) + (m.nbody if point[1] == "com" else 0)

    start = np.array([row(SEGMENTS[j][0]) for j in FEATURE_BODIES])
    end = np.array([row(SEGMENTS[j][1]) for j in FEATURE_BODIES])
    return SegmentIndex(root=body(ROOT_BODY), start=start, end=end)


def heading_rotation(xmat: np.ndarray) -> np.ndarray:
    """World → heading frame rotation (3×3) for a root body orientation ``xmat`` (3×3 or flat 9).

    Heading x = the root's x axis projected on the horizontal plane, normalised; when that axis is
    vertical (nose straight up or down) the root's y axis, which is then horizontal, gives the left
    direction instead. z stays world up. A matrix that is no rotation (e.g. an MjData never
    forwarded: all zeros) is a `ParameterError`.
    """
    r = np.asarray(xmat, dtype=float).ravel()  # row-major: r[3·row + col]
    if r.size != 9:
        raise ParameterError(f"root orientation must be a 3×3 matrix, got {np.shape(xmat)}")
    hx, hy = float(r[0]), float(r[3])
    norm = math.hypot(hx, hy)
    if norm < 1e-9:
        hx, hy = float(r[4]), -float(r[1])  # heading x = root y axis turned −90° about z
        norm = math.hypot(hx, hy)
        if not norm > 0.5:  # a rotation's y axis is horizontal here; zeros or NaN: no kinematics yet
            raise ParameterError("root orientation is not a rotation (run mj_forward before body_frame)")
    c, s = hx / norm, hy / norm
    return np.array(((c, s, 0.0), (-s, c, 0.0), (0.0, 0.0, 1.0)))


def body_frame(m: mujoco.MjModel, d: mujoco.MjData, index: SegmentIndex | None = None) -> np.ndarray:
    """Segment vectors r_j (J×3, metres) of the present MjData in the heading frame.

    Uses the kinematics already in ``d`` (valid after ``mj_step``/``mj_forward``/``mj_kinematics``).
    Rows in `FEATURE_BODIES` order; see the module docstring for the points each vector joins.
    """
    ix = index if index is not None else segment_index(m)
    points = np.concatenate((d.xpos, d.xipos))
    return (points[ix.end] - points[ix.start]) @ heading_rotation(d.xmat[ix.root]).T


MOTION_PREFIX = "felis_motion_"


def motion_sensors(ms: mujoco.MjSpec) -> None:
    """An `MjSpec` edit (`felis.sim.batch.DropBatch`'s ``sensors``) adding what `body_frame` reads, as sensors:
    each body's frame origin (``xpos``) and centre of mass (``xipos``), the root's x and y axes, and the lower
    body's z axis (training's landing score uses it)."""
    m = ms.compile()
    O, S = mujoco.mjtObj, mujoco.mjtSensor
    for b in range(1, m.nbody):
        name = m.body(b).name
        ms.add_sensor(name=f"{MOTION_PREFIX}x_{name}", type=S.mjSENS_FRAMEPOS, objtype=O.mjOBJ_XBODY, objname=name)
        ms.add_sensor(name=f"{MOTION_PREFIX}i_{name}", type=S.mjSENS_FRAMEPOS, objtype=O.mjOBJ_BODY, objname=name)
    ms.add_sensor(name=MOTION_PREFIX + "rootx", type=S.mjSENS_FRAMEXAXIS, objtype=O.mjOBJ_XBODY, objname=ROOT_BODY)
    ms.add_sensor(name=MOTION_PREFIX + "rooty", type=S.mjSENS_FRAMEYAXIS, objtype=O.mjOBJ_XBODY, objname=ROOT_BODY)
    ms.add_sensor(name=MOTION_PREFIX + "lowerz", type=S.mjSENS_FRAMEZAXIS, objtype=O.mjOBJ_XBODY, objname="lower_body")


class SensorMotion:
    """`body_frame` from the sensors of `motion_sensors` (a batch's sensor data): ``vectors(sd)`` for rows
    of sensor data (N, nsensordata) gives (N, J, 3); ``lower_up_z(sd)`` the lower body's up-axis z (N,)."""

    def __init__(self, m: mujoco.MjModel):
        self.index = segment_index(m)

        def adr(name: str) -> int:
            sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, MOTION_PREFIX + name)
            if sid < 0:
                raise ParameterError(f"the model lacks the motion sensor {MOTION_PREFIX + name!r} (motion_sensors)")
            return int(m.sensor_adr[sid])

        rows = np.zeros((2 * m.nbody, 3), dtype=int)  # sensor addresses of xpos, then xipos; world: -1
        rows[0] = rows[m.nbody] = -1
        for b in range(1, m.nbody):
            rows[b] = adr("x_" + m.body(b).name) + np.arange(3)
            rows[m.nbody + b] = adr("i_" + m.body(b).name) + np.arange(3)
        self._start, self._end = rows[self.index.start], rows[self.index.end]
        self._x, self._y, self._lz = adr("rootx"), adr("rooty"), adr("lowerz") + 2

    def vectors(self, sd: np.ndarray) -> np.ndarray:
        pts = lambda r: np.where(r >= 0, sd[:, np.maximum(r, 0)], 0.0)  # noqa: E731  (N, J, 3)
        v = pts(self._end) - pts(self._start)
        out = np.empty_like(v)
        for i in range(sd.shape[0]):
            x, y = sd[i, self._x:self._x + 3], sd[i, self._y:self._y + 3]
            z = np.cross(x, y)
            R = np.array([[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]])
            out[i] = v[i] @ heading_rotation(R).T
        return out

    def lower_up_z(self, sd: np.ndarray) -> np.ndarray:
        return sd[:, self._lz].copy()


class MotionRecorder:
    """Collects `body_frame` once per call of `record` (e.g. every 10 ms control tick of a rollout)."""

    def __init__(self, m: mujoco.MjModel):
        self.model = m
        self.index = segment_index(m)
        self._frames: list[np.ndarray] = []

    def record(self, d: mujoco.MjData) -> None:
        self._frames.append(body_frame(self.model, d, self.index))

    def __len__(self) -> int:
        return len(self._frames)

    def vectors(self) -> np.ndarray:
        """The recorded motion, (T, J, 3)."""
        if not self._frames:
            return np.zeros((0, len(FEATURE_BODIES), 3))
        return np.stack(self._frames)


# ---------------------------------------------------------------------------------------- features
def _finite(a: np.ndarray, what: str) -> None:
    if not np.isfinite(a).all():
        raise ParameterError(f"{what} holds non-finite values (NaN or inf)")


def logical_features(vectors: np.ndarray) -> np.ndarray:
    """b_j = (r_x > 0, r_y > 0, r_z > 0) per frame and body (eq. 2): (T, J, 3) floats → (T, J, 3) bool."""
    v = np.asarray(vectors, dtype=float)
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1:
        raise ParameterError(f"segment vectors must be (T≥1, J, 3), got shape {v.shape}")
    _finite(v, "segment vectors")
    return v > 0.0


def _bits(bits: np.ndarray) -> np.ndarray:
    b = np.asarray(bits)
    if b.ndim != 3 or b.shape[2] != 3 or b.shape[0] < 1:
        raise ParameterError(f"logical features must be (T≥1, J, 3), got shape {b.shape}")
    if b.dtype != bool:
        if not np.isin(b, (0, 1)).all():
            raise ParameterError("logical features must be booleans (0 or 1)")
        b = b.astype(bool)
    return b


def flatten_features(bits: np.ndarray) -> np.ndarray:
    """B (eq. 3): (T, J, 3) bool → (T, 3J) float of 0/1, B[t, 3j + k], k = front, left, above."""
    b = _bits(bits)
    return b.reshape(b.shape[0], -1).astype(float)


def joint_states(bits: np.ndarray) -> np.ndarray:
    """State of each b_j, s = 4·front + 2·left + above ∈ 0…7: (T, J, 3) bool → (T, J) int."""
    b = _bits(bits).astype(np.int64)
    return 4 * b[..., 0] + 2 * b[..., 1] + b[..., 2]


def transition_features(bits: np.ndarray) -> np.ndarray:
    """TF (eq. 5–6): P_j[s, s'] = #{t : s_j(t) = s, s_j(t+1) = s'} / T, shape (J, 8, 8).

    T is the number of frames (not of transitions), as in the paper; a single frame gives all zeros.
    """
    s = joint_states(bits)
    t, j = s.shape
    flat = (np.arange(j) * N_STATES * N_STATES)[None, :] + s[:-1] * N_STATES + s[1:]
    counts = np.bincount(flat.ravel(), minlength=j * N_STATES * N_STATES)
    return counts.reshape(j, N_STATES, N_STATES) / t


def transition_distance(tf: np.ndarray, tf2: np.ndarray) -> float:
    """S = Σ_j Σ |P_j − P′_j| over all matrix entries (eq. 8); 0 for equal motions."""
    a, b = np.asarray(tf, dtype=float), np.asarray(tf2, dtype=float)
    if a.ndim != 3 or a.shape[1:] != (N_STATES, N_STATES) or a.shape != b.shape:
        raise ParameterError(f"transition features must both be (J, 8, 8), got {a.shape} and {b.shape}")
    _finite(a, "transition features")
    _finite(b, "transition features")
    return float(np.abs(a - b).sum())


# ---------------------------------------------------------------------------------------- PCA
@dataclass(frozen=True)
class Pca:
    """Principal components of logical-feature rows B (eq. 3–4): L = (B − mean) · componentsᵀ.

    ``components`` (dims, F) are orthonormal rows, by decreasing variance; ``variance`` the variance of
    the data along each. Signs are fixed so each component's entry of largest magnitude is positive
    (the first such entry on a tie, ties judged to 1e-9 relative), so equal data give equal L on every
    machine. Identical columns (a leg and its foot) get equal entries, so such ties are common.
    """

    mean: np.ndarray
    components: np.ndarray
    variance: np.ndarray

    @classmethod
    def fit(cls, samples: np.ndarray, dims: int) -> Pca:
        """Fit on stacked rows B (N, F) of all motion samples; 1 ≤ dims ≤ F.

        With dims = F the basis is complete and `inverse_transform` rebuilds any B exactly.
        """
        x = np.asarray(samples, dtype=float)
        if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
            raise ParameterError(f"PCA samples must be (N≥1, F≥1) rows, got shape {x.shape}")
        _finite(x, "PCA samples")
        n, f = x.shape
        if not isinstance(dims, (int, np.integer)) or not 1 <= dims <= f:
            raise ParameterError(f"PCA dims must be an integer in 1…{f}, got {dims!r}")
        mean = x.mean(axis=0)
        _, sv, vt = np.linalg.svd(x - mean, full_matrices=True)
        comps = vt[:dims].copy()
        mag = np.abs(comps)  # near-ties (within 1e-9) go to the first index, robust to last-bit noise
        big = np.argmax(mag >= mag.max(axis=1, keepdims=True) * (1 - 1e-9), axis=1)
        comps *= np.where(comps[np.arange(dims), big] < 0, -1.0, 1.0)[:, None]
        var = np.zeros(f)
        var[: sv.size] = sv**2 / max(n - 1, 1)
        return cls(mean=mean, components=comps, variance=var[:dims])

    @property
    def dims(self) -> int:
        return self.components.shape[0]

    def transform(self, b: np.ndarray) -> np.ndarray:
        """L rows (T, dims) of B rows (T, F); the sequence of them is SF (eq. 4)."""
        x = np.asarray(b, dtype=float)
        f = self.mean.shape[0]
        if x.ndim != 2 or x.shape[1] != f:
            raise ParameterError(f"PCA input must be (T, {f}), got shape {x.shape}")
        _finite(x, "PCA input")
        return (x - self.mean) @ self.components.T

    def inverse_transform(self, l: np.ndarray) -> np.ndarray:  # noqa: E741
        """B rows rebuilt from L rows (exact when dims = F)."""
        y = np.asarray(l, dtype=float)
        if y.ndim != 2 or y.shape[1] != self.dims:
            raise ParameterError(f"PCA coordinates must be (T, {self.dims}), got shape {y.shape}")
        return y @ self.components + self.mean

    def to_arrays(self, prefix: str = "pca_") -> dict[str, np.ndarray]:
        """Plain arrays for an ``.npz`` (``np.savez(path, **pca.to_arrays(), **other)``)."""
        return {f"{prefix}mean": self.mean, f"{prefix}components": self.components,
                f"{prefix}variance": self.variance}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], prefix: str = "pca_") -> Pca:
        """Inverse of `to_arrays`; accepts an opened ``.npz``."""
        try:
            mean, comps, var = (np.asarray(arrays[f"{prefix}{k}"], dtype=float)
                                for k in ("mean", "components", "variance"))
        except KeyError as e:
            raise ParameterError(f"PCA arrays lack {e.args[0]!r}") from None
        if mean.ndim != 1 or comps.ndim != 2 or comps.shape[1] != mean.size or var.shape != (comps.shape[0],):
            raise ParameterError(f"PCA arrays have inconsistent shapes: mean {mean.shape}, components "
                                 f"{comps.shape}, variance {var.shape}")
        for a in (mean, comps, var):
            _finite(a, "PCA arrays")
        return cls(mean=mean, components=comps, variance=var)


# ---------------------------------------------------------------------------------------- DTW
def _sequence(a: np.ndarray, what: str) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim == 1:
        x = x[:, None]  # a sequence of scalars
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ParameterError(f"{what} must be (T≥1, dims) or (T≥1,), got shape {np.shape(a)}")
    _finite(x, what)
    return x


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = _sequence(a, "first sequence"), _sequence(b, "second sequence")
    if x.shape[1] != y.shape[1]:
        raise ParameterError(f"sequences differ in dims: {x.shape[1]} and {y.shape[1]}")
    return x, y


def dtw_table(cost: np.ndarray) -> float:
    """DTW[n, m] of a local-cost matrix c (n, m) ≥ 0, filled by anti-diagonals (module docstring).

    In the padded (n+1)×(m+1) table stored flat with row stride W = m + 1, cell (i, j) sits at
    i·W + j; one anti-diagonal i + j = k is the strided slice of step W − 1, and its up, left and
    diagonal neighbours are the same slice shifted by −W, −1 and −W − 1.
    """
    n, m = cost.shape
    w = m + 1
    table = np.full((n + 1) * w, np.inf)
    table[0] = 0.0
    padded = np.zeros((n + 1, w))
    padded[1:, 1:] = cost
    c = padded.ravel()
    step = w - 1
    tmp = np.empty(min(n, m))
    for k in range(2, n + m + 1):
        i0, i1 = max(1, k - m), min(n, k - 1)
        lo, hi = i0 * w + k - i0, i1 * w + k - i1 + 1
        t = tmp[: i1 - i0 + 1]
        np.minimum(table[lo - w:hi - w:step], table[lo - 1:hi - 1:step], out=t)
        np.minimum(t, table[lo - w - 1:hi - w - 1:step], out=t)
        np.add(t, c[lo:hi:step], out=table[lo:hi:step])
    return float(table[-1])


def dtw(a: np.ndarray, b: np.ndarray) -> float:
    """DTW(a, b) with local cost |a_i − b_j| (Euclidean), vectorised; equal to `dtw_reference`.

    a, b: (T, dims) sequences (1-D = scalars), any lengths ≥ 1.
    """
    x, y = _pair(a, b)
    return dtw_table(cdist(x, y))


def dtw_reference(a: np.ndarray, b: np.ndarray) -> float:
    """The paper's DTW as a plain double loop (§4.1), for tests."""
    x, y = _pair(a, b)
    xs, ys = x.tolist(), y.tolist()
    n, m = len(xs), len(ys)
    inf = float("inf")
    t = [[inf] * (m + 1) for _ in range(n + 1)]
    t[0][0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            d = sum((p - q) ** 2 for p, q in zip(xs[i - 1], ys[j - 1], strict=True)) ** 0.5
            t[i][j] = d + min(t[i - 1][j], t[i][j - 1], t[i - 1][j - 1])
    return t[n][m]


def motion_distance(sf: np.ndarray, sf2: np.ndarray) -> float:
    """D = ½(DTW(SF, SF′) + DTW(SF′, SF)) (eq. 7); ≥ 0, symmetric, 0 for identical sequences.

    The two terms are equal for this DTW (module docstring); both are computed, as eq. 7 reads, from
    one cost matrix and its transpose.
    """
    x, y = _pair(sf, sf2)
    cost = cdist(x, y)
    return 0.5 * (dtw_table(cost) + dtw_table(cost.T))
