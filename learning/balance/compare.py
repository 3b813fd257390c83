"""How a balance-strategy selector is judged (seed 004): the paper's RBF support-vector classifier for
comparison (`SvmSelector`, scikit-learn) and the accuracies of any selector on a case base. Training and
evaluation only; the controllers' selector is `felis.learning.balance.selector.KnnSelector`.
"""

from __future__ import annotations

import numpy as np

from felis.errors import SelectorError
from felis.learning.balance.selector import CaseBase, _Selector, standardisation


class SvmSelector(_Selector):
    """The paper's classifier for comparison: RBF ``SVC`` (scikit-learn) on standardised features,
    trained on the case labels. ``gamma`` is the kernel width g ("scale", "auto" or a number > 0)."""

    def __init__(self, C: float = 1.0, gamma: str | float = "scale"):
        C = float(C)
        if not np.isfinite(C) or C <= 0:
            raise SelectorError(f"C must be finite and > 0, not {C}")
        if isinstance(gamma, str):
            if gamma not in ("scale", "auto"):
                raise SelectorError(f"gamma must be 'scale', 'auto' or a number > 0, not {gamma!r}")
        else:
            gamma = float(gamma)
            if not np.isfinite(gamma) or gamma <= 0:
                raise SelectorError(f"gamma must be 'scale', 'auto' or a number > 0, not {gamma}")
        self.C, self.gamma = C, gamma
        self.mean = self.std = None  # type: ignore[assignment]
        self._svc = None
        self._only: int | None = None

    def fit(self, cases: CaseBase) -> SvmSelector:
        if not isinstance(cases, CaseBase):
            raise SelectorError(f"fit needs a CaseBase, not {type(cases).__name__}")
        from sklearn.svm import SVC  # lazily: the kNN path must not pay for scikit-learn

        self.feature_names, self.strategies = cases.feature_names, cases.strategies
        mean, std = standardisation(cases.features)
        y = cases.labels()
        classes = np.unique(y)
        if classes.size == 1:  # SVC needs two classes; one strategy everywhere is a constant rule
            self._svc, self._only = None, int(classes[0])
        else:
            self._svc = SVC(C=self.C, kernel="rbf", gamma=self.gamma).fit((cases.features - mean) / std, y)
            self._only = None
        self.mean, self.std = mean, std
        return self

    def _index(self, Z: np.ndarray) -> np.ndarray:
        if self._only is not None:
            return np.full(Z.shape[0], self._only, dtype=np.int64)
        return self._svc.predict(Z).astype(np.int64)


# -------------------------------------------------------------------------------------- evaluation


def _check_match(selector: _Selector, cases: CaseBase) -> None:
    selector._fitted()
    if tuple(selector.feature_names) != cases.feature_names:
        raise SelectorError(f"selector features {list(selector.feature_names)} differ from the cases' "
                            f"{list(cases.feature_names)}")
    if tuple(selector.strategies) != cases.strategies:
        raise SelectorError(f"selector strategies {list(selector.strategies)} differ from the cases' "
                            f"{list(cases.strategies)}")


def accuracy(selector: _Selector, cases: CaseBase, tol: float) -> float:
    """Fraction of cases whose predicted strategy is acceptable (score within ``tol`` of the best)."""
    _check_match(selector, cases)
    ok = cases.acceptable(tol)
    pred = selector.predict_index(cases.features)
    return float(ok[np.arange(len(cases)), pred].mean())


def exact_accuracy(selector: _Selector, cases: CaseBase) -> float:
    """Fraction of cases whose predicted strategy is the label (the argmin of the scores)."""
    _check_match(selector, cases)
    return float(np.mean(selector.predict_index(cases.features) == cases.labels()))

def recovery_accuracy(selector: _Selector, cases: CaseBase, fall: float = 1.0) -> float:
    """Fraction of rows where the pick recovers (score < ``fall``) whenever some strategy does: a pick
    counts as the best unless another strategy would have kept the robot up where it does not."""
    _check_match(selector, cases)
    pick = selector.predict_index(cases.features)
    s = np.asarray(cases.scores)
    picked = s[np.arange(len(s)), pick]
    return float(np.mean((picked < fall) | (s.min(axis=1) >= fall)))
