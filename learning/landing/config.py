"""Settings of the landing evolution (`felis.learning.landing.train`): `TrainConfig` and its validation.

Every setting but `RUNTIME_FIELDS` decides the numbers, so those are what a checkpoint must match to be
resumed and what the results file records.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.nets import MAX_HIDDEN
from felis.learning.landing.samples import STEPS

RUNTIME_FIELDS = ("workers", "ray_address")  # settings that never change the numbers
FITNESSES = ("eq9", "landing")


@dataclass(frozen=True)
class TrainConfig:
    """Settings of `train_landing`.

    ``population``: individuals per population (one population per training orientation in the simple
    stage; compose units in the complex stage). ``generations_simple`` / ``generations_complex``: the
    length of each stage. ``elite_frac``: the best floor(frac·N) (at least 1) pass unchanged;
    ``elimination_frac``: the worst floor(frac·N) are replaced by random immigrants (§5). ``tournament``:
    tournament size for picking parents among the survivors; ``p_crossover``: chance a child has two
    parents. ``p_weight``, ``sigma``, ``p_structure``, ``max_hidden``: `nets.mutate`'s settings
    (``max_hidden`` also bounds random units). ``pca_dims``: components of the PCA (eq. 4).
    ``orientations``: indices into the samples file (empty: all of them). ``use_similarity``: rank by
    (f, D, S) (eq. 10); False ranks by f alone (§6.6.1, experiment 1). ``smooth_upright``: f uses the
    upright ramp instead of the 0/1 test. ``steps``: rollout length in 10 ms ticks (§6.4: 200).
    ``samples``: motion samples file (`samples.load_samples`; "" = `DEFAULT_SAMPLES`).
    ``fitness``: "eq9" (the paper's eq. 9 × upright, `nets.fitness`) or "landing" (our
    `nets.landing_score`, partial credit for each clause of the `landed` rule). ``one_net``: instead
    of simple then complex, one simple behaviour evolves on every training orientation at once for
    ``generations_simple + generations_complex`` generations, ranked by eq. 11 (§6.6.2's baseline).
    ``generations_general`` (0 = none): a last stage, ours, that evolves one simple behaviour on
    ``general_drops`` random drops per generation (new ones each generation, from 1 m and 3 m in turn,
    start tilt at most ``general_max_tilt_deg``), seeded with the previous stages' simple behaviours and
    one that holds still (passive); its best is then the policy.
    ``design``: the cat the rollouts run on, one of `felis.learning.landing.designs.DESIGNS` (its servos, paws
    and physics step; default ``cat``, the described one; the shipped nets were trained on the cat as described
    until 2026-11-29, now ``4ms-paw``).
    ``workers``/``ray_address``: where rollouts run (`make_evaluator`); they never change the results.
    """

    seed: int = 0
    population: int = 24
    generations_simple: int = 200
    generations_complex: int = 100
    elite_frac: float = 0.1
    elimination_frac: float = 0.2
    tournament: int = 2
    p_crossover: float = 0.5
    p_weight: float = 0.1
    sigma: float = 0.1
    p_structure: float = 0.05
    max_hidden: int = MAX_HIDDEN
    pca_dims: int = 8
    orientations: tuple[int, ...] = ()
    use_similarity: bool = True
    smooth_upright: bool = False
    steps: int = STEPS
    samples: str = ""
    fitness: str = "eq9"
    one_net: bool = False
    generations_general: int = 0
    general_drops: int = 16
    general_max_tilt_deg: float = 180.0
    design: str = "cat"
    workers: int | None = None
    ray_address: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "orientations", tuple(self.orientations) if isinstance(
            self.orientations, list | tuple) else self.orientations)
        self.check()

    @property
    def n_elite(self) -> int:
        return max(1, int(math.floor(self.elite_frac * self.population + 1e-9)))

    @property
    def n_eliminate(self) -> int:
        return int(math.floor(self.elimination_frac * self.population + 1e-9))  # as eliminate_and_immigrate

    def check(self) -> TrainConfig:
        """One-line `ParameterError` for the first bad setting; returns the config."""
        def integer(name: str, lo: int, none_ok: bool = False) -> None:
            v = getattr(self, name)
            if v is None and none_ok:
                return
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
                raise ParameterError(f"training {name} must be an integer ≥ {lo}, got {v!r}")

        def fraction(name: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0.0 <= v <= 1.0:
                raise ParameterError(f"training {name} must be a number in [0, 1], got {v!r}")

        integer("seed", 0)
        integer("population", 2)
        integer("generations_simple", 1)
        integer("generations_complex", 1)
        integer("generations_general", 0)
        integer("general_drops", 1)
        t = self.general_max_tilt_deg
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0.0 < t <= 180.0:
            raise ParameterError(f"training general_max_tilt_deg must be a number in (0, 180], got {t!r}")
        integer("tournament", 1)
        integer("max_hidden", 1)
        integer("pca_dims", 1)
        integer("steps", 2)
        integer("workers", 1, none_ok=True)
        for name in ("elite_frac", "elimination_frac", "p_crossover", "p_weight", "p_structure"):
            fraction(name)
        if isinstance(self.sigma, bool) or not isinstance(self.sigma, int | float) or not (
                math.isfinite(self.sigma) and self.sigma >= 0):
            raise ParameterError(f"training sigma must be a finite number ≥ 0, got {self.sigma!r}")
        if self.n_elite + self.n_eliminate > self.population - 1:
            raise ParameterError(f"training keeps {self.n_elite} elites and replaces {self.n_eliminate} of "
                                 f"{self.population} individuals: leave room for at least one child (lower "
                                 "elite_frac or elimination_frac)")
        o = self.orientations
        if not isinstance(o, tuple) or any(isinstance(i, bool) or not isinstance(i, int | np.integer) or i < 0
                                           for i in o):
            raise ParameterError(f"training orientations must be sample indices (integers ≥ 0), got {o!r}")
        if len(set(o)) != len(o):
            raise ParameterError(f"training orientations {list(o)} name a sample twice")
        if self.fitness not in FITNESSES:
            raise ParameterError(f"training fitness must be one of {', '.join(FITNESSES)}, got {self.fitness!r}")
        for name in ("use_similarity", "smooth_upright", "one_net"):
            if not isinstance(getattr(self, name), bool):
                raise ParameterError(f"training {name} must be true or false, got {getattr(self, name)!r}")
        from felis.learning.landing.designs import DESIGNS  # late: the designs need the robot descriptions

        if self.design not in DESIGNS:
            raise ParameterError(f"training design must be one of {', '.join(DESIGNS)}, got {self.design!r}")
        if not isinstance(self.samples, str):
            raise ParameterError(f"training samples must be a file path (text), got {self.samples!r}")
        if self.ray_address is not None and (not isinstance(self.ray_address, str) or not self.ray_address.strip()):
            raise ParameterError(f"training ray_address must be 'local' or a cluster address, got {self.ray_address!r}")
        return self

    def as_dict(self) -> dict:
        d = asdict(self)
        d["orientations"] = [int(i) for i in self.orientations]
        return d

    def results_settings(self) -> dict:
        """The settings that decide the numbers (all but `RUNTIME_FIELDS`)."""
        return {k: v for k, v in self.as_dict().items() if k not in RUNTIME_FIELDS}
