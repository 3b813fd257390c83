"""Controllers and monitors (`felis.controllers`): pure functions of HAL state and time.

They import only `felis` core, `felis.scenarios` and the inference modules of `felis.learning`
(`landing.policy`, `ik.solver`, `phase.estimator`, `balance.selector`: numpy, no torch), never a backend,
so each runs unchanged on simulated and real robots. `make_controller` builds one by name for the CLI.

    pose.py          PoseController: hold, stand, sit, or any pose with time-based interpolation
    keyframes.py     KeyframeController: minimum-jerk moves through taught or named poses (felis pose play)
    stepping.py      SteppingController: the cat trots in place
    balance.py       BalanceMonitor: the XCoM balance monitor (seed 004)
    reactions.py     protective reactions and ReactiveController, which runs them on the monitor's alarm
    landing.py       LandingController: a falling cat's policy (seed 000)
    arm_track.py     ArmTrackController: the arm tracking a tool-point trajectory with the learned IK (seed 001)
    arm_posture.py   the arm's posture rule: the joint angles a demonstrator gives a tool-point path
    trajectories.py  Trajectory: the arm's tool-point trajectories (builtin, CSV files)
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

from felis.controllers.arm_track import LEAD_IN, ArmTrackController, trajectory_from
from felis.controllers.balance import BalanceMonitor
from felis.controllers.keyframes import keyframes
from felis.controllers.landing import LandingController
from felis.controllers.pose import PoseController
from felis.controllers.reactions import FEATURES, REACTIONS, ReactiveController
from felis.controllers.stepping import SteppingController
from felis.errors import ParameterError
from felis.hal import Controller
from felis.learning.balance.selector import load_selector
from felis.learning.ik.solver import IkSolver
from felis.learning.landing.motion import is_motion_file, load_motion
from felis.learning.landing.policy import DEFAULT_POLICY, load_policy
from felis.learning.phase.estimator import PhaseEstimator


def _arm_track(trajectory="figure8", weights=None, lead_in: float | None = None, hold: float = 0.0) -> Controller:
    """The arm following a tool-point trajectory (a builtin name, a CSV file or a Trajectory) with the
    learned IK pipeline (weights: the shipped ones unless a file is given), after holding its first point
    ``hold`` seconds."""
    return ArmTrackController(trajectory_from(trajectory), IkSolver.load(weights),
                              lead_in=LEAD_IN if lead_in is None else lead_in, hold=hold)


def _step_in_place(frequency_hz: float = 2.0, lift: float = 0.5) -> Controller:
    """The cat trotting in place (diagonal pairs in turn)."""
    return SteppingController(frequency_hz=frequency_hz, lift=lift)


GATES = ("clock", "phase", "none")


class _Observed:
    """A controller with loop-side observers fed each tick's state before it runs (the phase estimator
    that its balance monitor's gait gate reads)."""

    def __init__(self, controller, *observers):
        self.controller, self.observers = controller, observers
        self.name = getattr(controller, "name", type(controller).__name__)

    def reset(self, spec, state) -> None:
        for o in self.observers:
            o.reset(spec, state)
        self.controller.reset(spec, state)

    def __call__(self, state):
        for o in self.observers:
            o(state)
        return self.controller(state)

    def __getattr__(self, name):  # alarm_t, strategy, assessment … of the wrapped controller
        return getattr(self.controller, name)


def _balance(base: str = "stand", reaction: str = "none", body=None, selector=None, gate: str = "clock") -> Controller:
    """A base controller (stand, step-in-place) guarded by the XCoM balance monitor and a protective
    reaction (none, brace, crouch, step, or selector: the shipped strategy selector; ``selector`` a
    selector file). ``body`` is the robot's `felis.bodymodel.BodyModel`; the CLI passes it in. ``gate``
    feeds the monitor's gait gate: ``clock`` the base's own gait clock, ``phase`` the learned phase
    estimator (`felis.learning.phase.estimator`, shipped weights) reading the joints, ``none`` nothing."""
    if body is None:
        raise ParameterError("controller 'balance' needs the robot's body model (the felis command provides it)")
    if base not in ("stand", "step-in-place"):
        raise ParameterError(f"balance: base must be stand or step-in-place, got {base!r}")
    if reaction == "selector":
        react = load_selector(selector, feature_names=FEATURES)
    elif reaction in REACTIONS:
        react = reaction
    else:
        raise ParameterError(f"balance: unknown reaction {reaction!r}; known: {', '.join(REACTIONS)}, selector")
    if gate not in GATES:
        raise ParameterError(f"balance: unknown gate {gate!r}; known: {', '.join(GATES)}")
    monitor = BalanceMonitor(body)
    if gate == "none":
        monitor.gait = lambda t: None  # not the base's clock either
    ctl = ReactiveController(make_controller(base), monitor, react)
    if gate == "phase":
        est = PhaseEstimator()
        monitor.gait = est.gait
        return _Observed(ctl, est)
    return ctl


def _landing(policy=None, drop_height: float | None = None) -> Controller:
    """The falling cat's landing policy: ``caps+library`` (at each height a vote by attitude between the shipped cap
    policy made for it, `felis.learning.landing.cap_policy`, and the shipped motion library,
    `felis.learning.landing.library`: `felis.learning.landing.by_height`, `felis.learning.landing.by_attitude`) where
    both are shipped, else the library, else the shipped evolved nets (seed 000), unless a policy is named:
    ``caps+library``, ``library``, ``shipped`` (the nets), ``caps`` (the cap policy at every height), a caps or a
    vote ``.json`` file, a ``.npz`` file of
    nets, a ``.json`` motion library, or a ``.json`` open-loop whole-body motion searched for one drop
    (`felis.learning.landing.motion`), which must run from the height it was searched for. ``drop_height``
    (m): the drop's, which the library times its motion by and where the robot reports no height (hardware) the
    free-fall prediction starts from."""
    from felis.learning.landing.by_attitude import is_vote_file, vote_rule
    from felis.learning.landing.by_height import NAME, caps_library_rule
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, is_caps_file, load_cap_rule
    from felis.learning.landing.library import DEFAULT_LIBRARY, LibraryRule, is_library_file, load_library

    if policy is None:
        policy = (NAME if SHIPPED_CAPS.is_file() else "library") if DEFAULT_LIBRARY.is_file() else None
    if policy is not None and str(policy) == NAME:
        return LandingController(caps_library_rule(SHIPPED_CAPS, load_library(DEFAULT_LIBRARY), drop_height),
                                 drop_height=drop_height)
    if policy is not None and is_vote_file(policy):
        return LandingController(vote_rule(policy, load_library(DEFAULT_LIBRARY), drop_height), drop_height=drop_height)
    if policy is not None and (str(policy) == "caps" or is_caps_file(policy)):
        return LandingController(load_cap_rule(SHIPPED_CAPS if str(policy) == "caps" else policy),
                                 drop_height=drop_height)
    if policy is not None and str(policy) in ("library", "shipped"):
        if str(policy) == "shipped":
            policy = DEFAULT_POLICY
        else:
            return LandingController(LibraryRule(load_library(DEFAULT_LIBRARY), drop_height), drop_height=drop_height)
    if policy is not None and is_motion_file(policy):
        if is_library_file(policy):
            return LandingController(LibraryRule(load_library(policy), drop_height), drop_height=drop_height)
        rule, _ = load_motion(policy)  # ParameterError: one line
        if drop_height is not None and abs(drop_height - rule.height_m) > 1e-6:
            raise ParameterError(f"{policy}: a motion timed for a drop from {rule.height_m:g} m, not "
                                 f"{drop_height:g} m: run it with --height {rule.height_m:g}")
        return LandingController(rule, drop_height=drop_height)
    behaviour, _ = load_policy(DEFAULT_POLICY if policy is None else policy)  # PolicyError: one line
    return LandingController(behaviour, drop_height=drop_height)


CONTROLLERS: dict[str, Callable[..., Controller]] = {
    "hold": lambda: PoseController("hold"),
    "stand": lambda: PoseController("stand", duration=0.5),
    "sit": lambda: PoseController("sit", duration=1.5),
    "zero": lambda: PoseController("zero", duration=1.0),
    "arm-track": _arm_track,
    "step-in-place": _step_in_place,
    "balance": _balance,
    "landing": _landing,
    "keyframes": keyframes,
}


def make_controller(name: str, **options) -> Controller:
    """A fresh controller by name with its options; ParameterError lists the known names or options."""
    try:
        factory = CONTROLLERS[name]
    except KeyError:
        raise ParameterError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}") from None
    try:
        inspect.signature(factory).bind(**options)
    except TypeError:
        known = ", ".join(inspect.signature(factory).parameters) or "none"
        raise ParameterError(f"controller {name!r} does not take {', '.join(options)} (its options: {known})") from None
    return factory(**options)


__all__ = ["CONTROLLERS", "PoseController", "make_controller"]
