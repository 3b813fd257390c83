"""Reactive-strategy selection after a push: which protective strategy to run when the balance
monitor warns, learned from demonstrations.

Source: seed 004 (``004_f10fd18fee8ce04e.txt``) §1.4, learning from demonstration, and its §3
experiment (``shared/reference/methods.md``, "Balance under disturbance"): an SVM predicting the
strategy type reached 96% accuracy after training on 600 samples (90–96% when the push force changed
without retraining).

Data. At the warning a feature vector s ∈ ℝᵐ is recorded (margin of stability, XCoM offset direction,
CoM velocity, gait phase, …; this module is generic in m and in the names). A demonstration tries every
strategy of `STRATEGIES` on the same push in simulation and scores each outcome, lower being better
(e.g. 0 = recovered cleanly, ≥ 1 = fell). A `CaseBase` holds n such rows: features (n, m) and scores
(n, k). A case's label is its best strategy (argmin of its scores; on a tie the earlier strategy);
its action is the one-hot vector a ∈ {0, 1}ᵏ of that label.

"Acceptable" (`CaseBase.acceptable`, `accuracy`): several strategies often recover equally well, so a
strategy whose score is within ``tol`` of the row's best counts as a best one::

    acceptable[i, j] = scores[i, j] ≤ min_l scores[i, l] + tol

`accuracy` is the fraction of rows whose predicted strategy is acceptable; `exact_accuracy` the fraction
equal to the label.

Standardisation. Both selectors see ŝ = (s − μ) / σ with μ, σ the per-feature mean and standard
deviation of the training features (σ = 1 for a constant feature), so γ below is in units of σ.

Denoising (eq. 5). Demonstrations are noisy (a push near a boundary, a simulation that happened to
fall); the case base D is thinned to D' such that near states map to near actions::

    ‖ŝ − ŝ'‖ ≤ γ  ⇒  ‖a − a'‖ ≤ δ        for all (s, a), (s', a') ∈ D'        (5)

With one-hot actions ‖a − a'‖ is 0 or √2, so any δ < √2 means "cases closer than γ share a label".
`denoise` drops, one at a time, the case that violates (5) with the most others (ties: the one that
agrees with the fewest of its γ-neighbours, i.e. sits deepest in a neighbourhood of another label; then
the lowest index), until no violating pair remains. A mislabelled case inside a cluster goes first; a
clean case base is kept whole.

Continuous k-nearest-neighbour interpolation (`KnnSelector`). Over the k nearest kept cases N(s)
(Euclidean distance dᵢ in standardised units), Shepard's inverse-distance weights::

    a(s) = Σ_{i∈N(s)} wᵢ aᵢ / Σ_{i∈N(s)} wᵢ,      wᵢ = dᵢ^(−p)     (p = ``power``, 1 by default)

and where some dᵢ = 0 (a query on a stored case) only those cases weigh. a(s) is a point of the
probability simplex (it sums to 1), varies continuously with s, and reproduces a stored case's
action exactly; the selected strategy is argmax a(s) (ties: the earlier strategy).

With ``interpolate="scores"`` the same weights interpolate the cases' outcome scores instead of their
one-hot labels, â(s) = Σ wᵢ scoresᵢ / Σ wᵢ, the expected outcome of each strategy near s, and the
selected strategy is argmin â(s). A neighbour that fell (score ≥ 1) then outweighs two that tilted a
little less, which suits a protective reaction: on the cat's held-out pushes it picks a strategy that
recovers whenever one does on 99.3 % of them, against 93.2 % interpolating labels (docs/balance.md).
The shipped selector (``learning/weights/balance_selector.npz``, `felis train balance`) uses it with
k = 7, p = 2. `recovery_accuracy` is that measure.

SVM (`SvmSelector`), the paper's classifier, for comparison: scikit-learn's ``SVC`` with an RBF kernel
K(ŝ, ŝ') = exp(−g ‖ŝ − ŝ'‖²) (g = ``gamma``; "scale" is 1 / (m · var ŝ)) and box constraint C,
one-vs-one over the strategies, on the standardised features and labels. Deterministic
(no probability calibration).

Measured (``tests/learning/test_balance_select.py``: a synthetic outcome model on 4 features, 600 training
demonstrations with 5% corrupted labels, 1000 clean held-out pushes): acceptable-strategy accuracy
(tol 0.05) kNN 0.970 (exact 0.869), SVM 0.993 (exact 0.903). Denoising with the defaults (k = 7,
γ = 0.3) is neutral there (0.971 without): the distance-weighted vote already outvotes isolated
errors, and a γ large enough to reach them also carves a γ-wide gap along every true boundary (eq. 5
forbids differing labels closer than γ). It pays where one neighbour decides: k = 1, 15% noise,
γ = 0.6 → 0.886 vs 0.825.

Files. `KnnSelector.save` writes one ``.npz`` (no pickled objects), atomically: the kept case base
(``features``, ``scores``), the standardisation (``mean``, ``std``) and a JSON string ``__meta__``
with the format tag, version, feature and strategy names and parameters. `KnnSelector.load` refuses a
missing, corrupt, truncated, foreign or mismatched file with one-line `SelectorError`.

The SVM and the accuracies are in `felis.learning.balance.compare` (training and evaluation); this module
is what controllers load: the case base, denoising, the kNN selector and its file, numpy only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import SelectorError
from felis.files import META_KEY, read_meta, read_npz, write_atomic

STRATEGIES: tuple[str, ...] = ("none", "brace", "crouch", "step")

FORMAT = "felis-balance-select"
VERSION = 1
_HIT = 1e-12  # distance (standardised units) below which a query counts as on a stored case



# ------------------------------------------------------------------------------------------- cases


def _names(value: Any, what: str) -> tuple[str, ...]:
    if isinstance(value, str):
        raise SelectorError(f"{what} must be a sequence of names, not the single string {value!r}")
    try:
        names = tuple(value)
    except TypeError:
        raise SelectorError(f"{what} must be a sequence of names, not {type(value).__name__}") from None
    bad = [n for n in names if not isinstance(n, str) or not n.strip()]
    if bad:
        raise SelectorError(f"{what} must be non-empty strings; got {bad[0]!r}")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SelectorError(f"{what} repeat {', '.join(map(repr, dup))}")
    return names


def _array(value: Any, what: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)  # a copy: the case base must not change under its owner
    except (TypeError, ValueError):
        raise SelectorError(f"{what} must be real numbers") from None
    return arr


def _finite(arr: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        where = np.argwhere(bad)[0]
        raise SelectorError(f"{what} hold {int(bad.sum())} non-finite value(s), first at index "
                            f"{tuple(int(i) for i in where)}")


@dataclass(frozen=True, eq=False)  # eq on arrays is ambiguous: identity equality, hashable
class CaseBase:
    """Demonstrations: ``features`` (n, m) at the alarm, ``scores`` (n, k) of each strategy's outcome
    (lower is better), one column per name in ``strategies``. Arrays are copied and made read-only."""

    features: np.ndarray
    scores: np.ndarray
    feature_names: tuple[str, ...]
    strategies: tuple[str, ...] = STRATEGIES

    def __post_init__(self) -> None:
        names = _names(self.feature_names, "feature names")
        strategies = _names(self.strategies, "strategies")
        X = _array(self.features, "features")
        Y = _array(self.scores, "scores")
        if X.ndim != 2:
            raise SelectorError(f"features must be a 2-D array (cases, features), not shape {X.shape}")
        if Y.ndim != 2:
            raise SelectorError(f"scores must be a 2-D array (cases, strategies), not shape {Y.shape}")
        if X.shape[0] < 1:
            raise SelectorError("the case base holds no cases")
        if X.shape[0] != Y.shape[0]:
            raise SelectorError(f"features hold {X.shape[0]} cases but scores {Y.shape[0]}")
        if X.shape[1] != len(names):
            raise SelectorError(f"features have {X.shape[1]} columns but {len(names)} feature names")
        if len(strategies) < 1:
            raise SelectorError("no strategies")
        if Y.shape[1] != len(strategies):
            raise SelectorError(f"scores have {Y.shape[1]} columns but {len(strategies)} strategies")
        _finite(X, "features")
        _finite(Y, "scores")
        X.setflags(write=False)
        Y.setflags(write=False)
        object.__setattr__(self, "features", X)
        object.__setattr__(self, "scores", Y)
        object.__setattr__(self, "feature_names", names)
        object.__setattr__(self, "strategies", strategies)

    def __len__(self) -> int:
        return self.features.shape[0]

    def labels(self) -> np.ndarray:
        """Index of each case's best strategy (argmin of its scores; ties → the earlier strategy)."""
        return np.argmin(self.scores, axis=1)

    def acceptable(self, tol: float) -> np.ndarray:
        """Bool (n, k): strategies whose score is within ``tol`` (≥ 0) of the row's best."""
        tol = float(tol)
        if not np.isfinite(tol) or tol < 0:
            raise SelectorError(f"tolerance must be a finite number ≥ 0, not {tol}")
        return self.scores <= self.scores.min(axis=1, keepdims=True) + tol

    def subset(self, index: np.ndarray) -> CaseBase:
        """The cases at ``index`` (integer indices or a boolean mask), same names."""
        return CaseBase(self.features[index], self.scores[index], self.feature_names, self.strategies)

    def split(self, fraction: float, seed: int) -> tuple[CaseBase, CaseBase]:
        """(train, held-out): a shuffle with ``numpy.random.default_rng(seed)`` puts round(fraction · n)
        cases in train, the rest held out; both keep the original order. Same seed, same split."""
        fraction = float(fraction)
        n = len(self)
        n_train = int(round(fraction * n))
        if not (0.0 < fraction < 1.0) or not 1 <= n_train <= n - 1:
            raise SelectorError(f"cannot split {n} case(s) with train fraction {fraction}: both parts "
                                "must hold at least one case")
        perm = np.random.default_rng(seed).permutation(n)
        return self.subset(np.sort(perm[:n_train])), self.subset(np.sort(perm[n_train:]))


def standardisation(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature (mean, std) of a (n, m) array; std 1 for a constant feature (it carries nothing)."""
    mean = features.mean(axis=0)
    std = features.std(axis=0)
    std = np.where(std > 1e-12 * np.maximum(1.0, np.abs(mean)), std, 1.0)
    return mean, std


def one_hot(labels: np.ndarray, k: int) -> np.ndarray:
    """(n, k) one-hot actions of integer labels."""
    A = np.zeros((len(labels), k))
    A[np.arange(len(labels)), labels] = 1.0
    return A


# ----------------------------------------------------------------------------------------- denoise


def _check_thresholds(gamma: float, delta: float) -> tuple[float, float]:
    gamma, delta = float(gamma), float(delta)
    if not np.isfinite(gamma) or gamma < 0:
        raise SelectorError(f"gamma (state distance, in standard deviations) must be finite and ≥ 0, not {gamma}")
    if not np.isfinite(delta) or delta < 0:
        raise SelectorError(f"delta (action distance) must be finite and ≥ 0, not {delta}")
    return gamma, delta


def _neighbours(Z: np.ndarray, radius: float, block: int = 512) -> list[np.ndarray]:
    """For each row of Z, the indices of the other rows within ``radius`` (blocked, O(n²) time,
    O(block · n) memory)."""
    n = Z.shape[0]
    sq = np.einsum("ij,ij->i", Z, Z)
    out: list[np.ndarray] = []
    r2 = radius * radius
    for lo in range(0, n, block):
        hi = min(n, lo + block)
        d2 = sq[lo:hi, None] + sq[None, :] - 2.0 * Z[lo:hi] @ Z.T
        # exact on the diagonal, and guard the cancellation error of the expansion near the radius
        d2[np.arange(hi - lo), np.arange(lo, hi)] = np.inf
        near = d2 <= r2 + 1e-9 * (1.0 + r2)
        for row in range(hi - lo):
            cand = np.flatnonzero(near[row])
            if cand.size:
                exact = np.sum((Z[cand] - Z[lo + row]) ** 2, axis=1)
                cand = cand[exact <= r2]
            out.append(cand)
    return out


def denoise(cases: CaseBase, gamma: float, delta: float) -> tuple[CaseBase, np.ndarray]:
    """Thin the case base until eq. 5 of seed 004 holds for every kept pair:
    ‖ŝ − ŝ'‖ ≤ γ ⇒ ‖a − a'‖ ≤ δ, with ŝ the features standardised over ``cases`` and a the one-hot
    action of the case's label.

    Iteratively drops the case that violates the condition with the most neighbours (ties: the one
    agreeing with the fewest of its γ-neighbours, i.e. furthest from its neighbourhood's majority;
    then the lowest index) until no violating pair remains. At least one case always remains.
    Returns (kept cases, boolean mask of kept rows of ``cases``).
    """
    gamma, delta = _check_thresholds(gamma, delta)
    mean, std = standardisation(cases.features)
    Z = (cases.features - mean) / std
    labels = cases.labels()
    k = len(cases.strategies)
    eye = np.eye(k)
    action_dist = np.linalg.norm(eye[:, None, :] - eye[None, :, :], axis=2)  # (k, k)
    conflict_pair = action_dist > delta

    nbrs = _neighbours(Z, gamma)
    conflicts = [nb[conflict_pair[labels[i], labels[nb]]] for i, nb in enumerate(nbrs)]
    agrees = [nb[~conflict_pair[labels[i], labels[nb]]] for i, nb in enumerate(nbrs)]
    n = len(cases)
    bad = np.array([c.size for c in conflicts], dtype=np.int64)
    good = np.array([a.size for a in agrees], dtype=np.int64)
    kept = np.ones(n, dtype=bool)
    order = np.arange(n)
    while True:
        live = np.flatnonzero(kept & (bad > 0))
        if live.size == 0:
            break
        # most violations, then fewest agreeing neighbours, then lowest index
        pick = live[np.lexsort((order[live], good[live], -bad[live]))[0]]
        kept[pick] = False
        c = conflicts[pick]
        bad[c[kept[c]]] -= 1
        a = agrees[pick]
        good[a[kept[a]]] -= 1
        bad[pick] = good[pick] = 0
    return cases.subset(kept), kept


# --------------------------------------------------------------------------------------- selectors


class _Selector:
    """Common query handling: checks, standardisation, strategy names."""

    feature_names: tuple[str, ...]
    strategies: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray

    def _fitted(self) -> None:
        if getattr(self, "mean", None) is None:
            raise SelectorError(f"{type(self).__name__} is not fitted: call fit(cases) or load a file first")

    def _queries(self, s: Any) -> tuple[np.ndarray, bool]:
        """(standardised (n, m) queries, whether the input was one vector)."""
        self._fitted()
        try:
            S = np.asarray(s, dtype=float)
        except (TypeError, ValueError):
            raise SelectorError("feature vector must be real numbers") from None
        single = S.ndim == 1
        if single:
            S = S[None, :]
        m = len(self.feature_names)
        if S.ndim != 2 or S.shape[1] != m:
            raise SelectorError(f"feature vector must have {m} values ({', '.join(self.feature_names)}) per row, "
                                f"not shape {np.shape(s)}")
        bad = ~np.isfinite(S)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise SelectorError(f"feature vector holds a non-finite value: {self.feature_names[col]} = "
                                f"{S[row, col]} (row {row})")
        return (S - self.mean) / self.std, single

    def _index(self, Z: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def predict_index(self, S: Any) -> np.ndarray:
        """Strategy indices (n,) for queries (n, m); a single (m,) vector gives shape (1,)."""
        Z, _ = self._queries(S)
        return self._index(Z)

    def __call__(self, s: Any) -> str:
        """The strategy for one feature vector (a selector is a reaction for `ReactiveController`)."""
        return str(self.predict(np.asarray(s, dtype=float).reshape(-1)))

    def predict(self, s: Any) -> str | list[str]:
        """The strategy name for one feature vector (m,); a list of names for (n, m)."""
        Z, single = self._queries(s)
        names = [self.strategies[i] for i in self._index(Z)]
        return names[0] if single else names


class KnnSelector(_Selector):
    """Denoised case base + continuous k-nearest-neighbour interpolation (seed 004 §1.4; formulas in
    the module docstring). ``gamma`` is in standard deviations of the features, ``delta`` in action
    units (one-hot: any δ < √2 means "neighbours share a label"); ``power`` is the inverse-distance
    exponent."""

    def __init__(self, k: int = 7, gamma: float = 0.3, delta: float = 0.5, denoise: bool = True,
                 power: float = 1.0, interpolate: str = "labels"):
        if interpolate not in ("labels", "scores"):
            raise SelectorError(f"interpolate must be 'labels' or 'scores', not {interpolate!r}")
        self.interpolate = interpolate
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise SelectorError(f"k (neighbours) must be an integer ≥ 1, not {k!r}")
        self.gamma, self.delta = _check_thresholds(gamma, delta)
        power = float(power)
        if not np.isfinite(power) or power <= 0:
            raise SelectorError(f"power (inverse-distance exponent) must be finite and > 0, not {power}")
        self.k = int(k)
        self.denoise = bool(denoise)
        self.power = power
        self.cases: CaseBase | None = None
        self.kept: np.ndarray | None = None  # mask over the cases given to fit (None after load)
        self.mean = self.std = None  # type: ignore[assignment]
        self._Z = self._A = None

    def fit(self, cases: CaseBase) -> KnnSelector:
        """Standardise over ``cases`` (μ, σ kept), denoise (eq. 5) if asked, store the kept cases."""
        if not isinstance(cases, CaseBase):
            raise SelectorError(f"fit needs a CaseBase, not {type(cases).__name__}")
        mean, std = standardisation(cases.features)
        if self.denoise:
            kept_cases, kept = denoise(cases, self.gamma, self.delta)
        else:
            kept_cases, kept = cases, np.ones(len(cases), dtype=bool)
        self._set(kept_cases, mean, std)
        self.kept = kept
        return self

    def _set(self, cases: CaseBase, mean: np.ndarray, std: np.ndarray) -> None:
        self.cases = cases
        self.feature_names, self.strategies = cases.feature_names, cases.strategies
        self.mean, self.std = mean, std
        self._Z = (cases.features - mean) / std
        if self.interpolate == "scores":  # every strategy's outcome, interpolated: the expected outcome
            self._A = np.asarray(cases.scores, dtype=float)
        else:
            self._A = one_hot(cases.labels(), len(cases.strategies))

    def action(self, s: Any) -> np.ndarray:
        """Interpolated action a(s) (k strategies, sums to 1): (k,) for one vector, (n, k) for (n, m).
        With ``interpolate="scores"``: the interpolated outcome score of each strategy (lower is better)."""
        Z, single = self._queries(s)
        out = self._action_z(Z)
        return out[0] if single else out

    def _action_z(self, Z: np.ndarray) -> np.ndarray:
        Zc, A = self._Z, self._A
        n, m = Zc.shape
        kk = min(self.k, n)
        block = max(1, 4_000_000 // (n * m))  # queries per block: ~32 MB of differences at most
        out = np.empty((Z.shape[0], A.shape[1]))
        for lo in range(0, Z.shape[0], block):
            q = Z[lo:lo + block]
            d = np.sqrt(np.sum((q[:, None, :] - Zc[None, :, :]) ** 2, axis=2))
            idx = np.argsort(d, axis=1, kind="stable")[:, :kk]
            dn = np.take_along_axis(d, idx, axis=1)
            hit = dn <= _HIT
            # w = d^-p, rescaled by the nearest neighbour's (d_1 / d)^p so a far query cannot underflow;
            # on a stored case only the cases at distance 0 weigh
            with np.errstate(divide="ignore", invalid="ignore"):
                w = (dn[:, :1] / dn) ** self.power
            w = np.where(hit.any(axis=1, keepdims=True), hit.astype(float), w)
            out[lo:lo + block] = np.einsum("qj,qjk->qk", w, A[idx]) / w.sum(axis=1, keepdims=True)
        return out

    def _index(self, Z: np.ndarray) -> np.ndarray:
        a = self._action_z(Z)
        return np.argmin(a, axis=1) if self.interpolate == "scores" else np.argmax(a, axis=1)

    # ------------------------------------------------------------------------------------ files

    def save(self, path: str | Path) -> Path:
        """Write the fitted selector to ``path`` (``.npz``, no pickle) atomically; returns the path."""
        self._fitted()
        path = Path(path)
        if path.suffix != ".npz":
            raise SelectorError(f"{path}: a selector file must end in .npz")
        meta = {"format": FORMAT, "version": VERSION, "feature_names": list(self.feature_names),
                "strategies": list(self.strategies), "k": self.k, "gamma": self.gamma, "delta": self.delta,
                "denoise": self.denoise, "power": self.power, "interpolate": self.interpolate,
                "cases": len(self.cases)}
        arrays = {"features": np.asarray(self.cases.features), "scores": np.asarray(self.cases.scores),
                  "mean": np.asarray(self.mean, dtype=float), "std": np.asarray(self.std, dtype=float),
                  META_KEY: np.array(json.dumps(meta, allow_nan=False))}
        return write_atomic(path, lambda f: np.savez(f, **arrays), "balance selector", SelectorError)

    @classmethod
    def load(cls, path: str | Path, feature_names: Any = None, strategies: Any = None) -> KnnSelector:
        """Read a file written by `save`. With ``feature_names`` / ``strategies``, the file's must be the
        same, in the same order. Every problem is a one-line `SelectorError` naming the file."""
        path = Path(path)
        data = read_npz(path, "selector", SelectorError)
        meta = read_meta(data, path, SelectorError, "balance-selector file", not_object=None,
                         ident=("format", FORMAT, "format {got!r} is not {want!r}; not a balance-selector file"),
                         version=("version", VERSION, "version {got!r} is not supported (felis reads {want})"))
        try:
            sel = cls(k=meta["k"], gamma=meta["gamma"], delta=meta["delta"], denoise=meta["denoise"],
                      power=meta["power"], interpolate=meta.get("interpolate", "labels"))
        except KeyError as e:
            raise SelectorError(f"{path}: metadata lacks {e.args[0]!r}") from None
        except SelectorError as e:
            raise SelectorError(f"{path}: bad parameter: {e}") from None
        missing = [key for key in ("features", "scores", "mean", "std") if key not in data]
        if missing:
            raise SelectorError(f"{path}: missing array(s) {', '.join(missing)}; truncated or not a selector file")
        try:
            cases = CaseBase(data["features"], data["scores"], meta.get("feature_names", ()),
                             meta.get("strategies", ()))
        except SelectorError as e:
            raise SelectorError(f"{path}: bad case base: {e}") from None
        m = len(cases.feature_names)
        if meta.get("cases") != len(cases):
            raise SelectorError(f"{path}: metadata says {meta.get('cases')} cases, arrays hold {len(cases)}")
        mean = np.asarray(data["mean"], dtype=float)
        std = np.asarray(data["std"], dtype=float)
        if mean.shape != (m,) or std.shape != (m,):
            raise SelectorError(f"{path}: mean/std have shapes {mean.shape}/{std.shape}, expected ({m},)")
        if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
            raise SelectorError(f"{path}: standardisation holds a non-finite mean or a std that is not > 0")
        _expect(path, "feature names", cases.feature_names, feature_names)
        _expect(path, "strategies", cases.strategies, strategies)
        sel._set(cases, mean, std)
        return sel


def _expect(path: Path, what: str, have: tuple[str, ...], want: Any) -> None:
    if want is None:
        return
    want = tuple(want)
    if have != want:
        raise SelectorError(f"{path}: {what} {list(have)} differ from the expected {list(want)}")


DEFAULT_SELECTOR = Path(__file__).parents[1] / "weights" / "balance_selector.npz"


def load_selector(path: str | Path | None = None, feature_names: Any = None) -> KnnSelector:
    """The strategy selector a controller uses (default: the shipped ``learning/weights/balance_selector.npz``,
    made by ``felis train balance``); callable features → strategy name."""
    return KnnSelector.load(DEFAULT_SELECTOR if path is None else path, feature_names=feature_names)
