"""Drop experiments on the simulated cat: one drop per episode, judged by the `landed` rule (issue 5).

An episode: the cat is reset to the model's pose (every joint at 0), turned and lifted by
`felis.sim.scenarios.apply_drop`, released at rest, and a policy runs in `felis.loop.run_loop` at 100 Hz for

    T = √(2h/g) + 1.0 s

(the fall, the 0.5 s after touchdown that the rule judges, and a margin). A `felis.sim.landing.LandingRecorder`
in the physics sub-step hook records, each physics step, the floor contacts, the tilt and the waist height,
and the peak ground force; `felis.scenarios.verdicts.landing_verdict` judges them (touchdown, any non-foot
contact in the window, the tilt and waist height at its end); the tilt at the end of the run is kept too.
The rule needs the cat's standing waist height: `standing_waist_height` measures it (it runs the ``stand``
controller, so it lives here, not in `felis.sim`).

Policies, by name: ``passive`` holds the pose the cat has at release (`make_controller("hold")`),
``stand`` moves to the stand pose (`make_controller("stand")`), ``rules`` runs the hand-written spine rule of
the nearest training orientation, ``shipped`` the shipped trained nets, ``library`` the shipped motion library
(`felis.learning.landing.library`), ``caps`` the shipped cap policy, ``caps+library`` the default
(`felis.learning.landing.by_height`), and a file path a trained policy (``.npz``), a motion library, a cap policy or
a vote between policies by attitude (`felis.learning.landing.by_attitude`) (``.json``) (`check_policy`).

`run_drops` runs a list of drops batched (`BatchLandingSim` on `felis.sim.batch.DropBatch`: every cat of a batch
stepped together by `mujoco.batch` on every core, the policy evaluated once per tick for the batch); results
are in drop order and identical whatever the thread count, and the physics is the sequential path's bit for bit.
`run_drops_sequential` is the one-episode-at-a-time path through `felis.loop.run_loop` in a process pool, which
the batch is tested against.
`summarise` gives the success rate (landed / drops) and one entry per drop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from felis.controllers import make_controller
from felis.errors import ParameterError, SimulationError
from felis.hal import Controller
from felis.learning.common.evaluator import run_jobs, worker_count
from felis.loop import run_loop
from felis.rotations import tilt_from_up
from felis.scenarios.drop import Drop
from felis.scenarios.verdicts import landing_verdict
from felis.sim import MujocoRobot
from felis.sim.landing import LandingRecorder
from felis.sim.scenarios import apply_drop, set_pose
from felis.spec import load_spec

RATE_HZ = 100.0
MARGIN_S = 1.0  # after the fall: the 0.5 s window and 0.5 s more

POLICIES = {"passive": "hold", "stand": "stand"}  # baseline name → controller name
NAMED = (*POLICIES, "rules", "shipped", "library", "caps", "caps+library")


def check_timestep_ms(ms: float) -> float:
    """``ms`` (a physics step in milliseconds) if a whole number of such steps fills the 10 ms control tick, else
    one-line `ParameterError`."""
    tick = 1000.0 / RATE_HZ
    if not (isinstance(ms, int | float) and math.isfinite(ms) and 0 < ms <= tick
            and abs(tick / ms - round(tick / ms)) < 1e-6):
        raise ParameterError(f"a physics step must divide the {tick:g} ms control tick, got {ms:g} ms")
    return float(ms)


def shipped_policy() -> Path:
    from felis.learning.landing.policy import DEFAULT_POLICY

    return DEFAULT_POLICY


def default_policy() -> str:
    """``caps+library`` (the shipped cap policy at its height, the shipped motion library at the others:
    `felis.learning.landing.by_height`) when both are shipped, else the motion library when it is, else the shipped
    trained nets, else ``passive``."""
    from felis.learning.landing.by_height import NAME
    from felis.learning.landing.cap_policy import SHIPPED_CAPS
    from felis.learning.landing.library import DEFAULT_LIBRARY

    if DEFAULT_LIBRARY.is_file():
        return NAME if SHIPPED_CAPS.is_file() else "library"
    return "shipped" if shipped_policy().is_file() else "passive"


def caps_path(policy: str) -> Path | None:
    """The cap policy a policy names (``caps``: the shipped one, or a caps ``.json`` file), else None."""
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, is_caps_file

    if policy == "caps":
        return SHIPPED_CAPS
    return Path(policy) if is_caps_file(policy) else None


def vote_path(policy: str) -> Path | None:
    """The vote between policies by attitude a policy names (a ``.json`` file that says it is one,
    `felis.learning.landing.by_attitude`), else None."""
    from felis.learning.landing.by_attitude import FORMAT
    from felis.learning.landing.cap_policy import json_format

    return Path(policy) if json_format(policy) == FORMAT else None


def library_path(policy: str) -> Path | None:
    """The motion library a policy names (``library`` or a ``.json`` file that is not a cap policy nor a vote), else
    None."""
    from felis.learning.landing.library import DEFAULT_LIBRARY

    if policy == "library":
        return DEFAULT_LIBRARY
    return (Path(policy) if Path(policy).suffix.lower() == ".json" and caps_path(policy) is None
            and vote_path(policy) is None else None)


def check_policy(policy: str) -> str:
    """``policy`` if it can be run: a baseline (passive, stand), ``rules`` (the hand-written spine rule of
    the nearest training orientation), ``shipped``, ``library``, ``caps``, ``caps+library`` or a policy file; else a
    one-line ParameterError."""
    if policy in POLICIES or policy == "rules":
        return policy
    if policy == "caps+library":  # both parts and the shipped votes (heights are checked where the policy is made)
        from felis.learning.landing.by_attitude import SHIPPED_VOTES, load_vote

        check_policy("caps")
        check_policy("library")
        for f in SHIPPED_VOTES:
            if f.is_file():
                load_vote(f)  # ParameterError: one line naming the file
        return policy
    vote = vote_path(policy)
    if vote is not None:  # the vote and each of its parts
        from felis.learning.landing.by_attitude import load_vote

        for part in load_vote(vote)[2]:
            check_policy(part)
        return policy
    caps = caps_path(policy)
    if caps is not None:
        from felis.learning.landing.cap_policy import load_caps

        if not caps.exists():
            raise ParameterError(f"--policy caps: no shipped cap policy {caps} (make one: bench/landing_caps.py)")
        load_caps(caps)  # ParameterError: one line naming the file
        return policy
    lib = library_path(policy)
    if lib is not None:
        from felis.learning.landing.library import load_library

        if not lib.exists():
            what = "no shipped motion library" if policy == "library" else "no such library file"
            raise ParameterError(f"--policy {policy}: {what} (make one: felis train landing-library)")
        load_library(lib)  # ParameterError: one line naming the file
        return policy
    from felis.learning.landing.policy import PolicyError, load_policy

    path = shipped_policy() if policy == "shipped" else Path(policy)
    if not path.exists():
        what = "no shipped landing policy" if policy == "shipped" else "no such policy file"
        raise ParameterError(f"--policy {policy}: {what} (policies: {', '.join(NAMED)} or a file from "
                             "`felis train landing`)")
    try:
        load_policy(path)
    except PolicyError as e:
        raise ParameterError(str(e)) from None
    return policy


def make_policy(policy: str, drop: Drop | None = None) -> Controller:
    """A fresh controller for a policy (`check_policy` first); ``rules`` needs the drop's orientation."""
    check_policy(policy)
    if policy in POLICIES:
        return make_controller(POLICIES[policy])
    from felis.controllers.landing import LandingController

    if policy == "rules":
        from felis.learning.landing.samples import nearest_rule

        rule = nearest_rule((drop.roll_deg, drop.pitch_deg, drop.yaw_deg) if drop else (180.0, 0.0, 0.0))
        return LandingController(rule, drop_height=drop.height_m if drop else None)
    if policy == "caps+library":
        from felis.learning.landing.by_height import caps_library_rule
        from felis.learning.landing.library import load_library

        h = drop.height_m if drop else None
        return LandingController(caps_library_rule(caps_path("caps"), load_library(), h), drop_height=h)
    vote = vote_path(policy)
    if vote is not None:
        from felis.learning.landing.by_attitude import vote_rule
        from felis.learning.landing.library import load_library

        h = drop.height_m if drop else None
        return LandingController(vote_rule(vote, load_library(), h), drop_height=h)
    caps = caps_path(policy)
    if caps is not None:
        from felis.learning.landing.cap_policy import load_cap_rule

        return LandingController(load_cap_rule(caps), drop_height=drop.height_m if drop else None)
    lib = library_path(policy)
    if lib is not None:
        from felis.learning.landing.library import LibraryRule, load_library

        return LandingController(LibraryRule(load_library(lib), drop.height_m if drop else None),
                                 drop_height=drop.height_m if drop else None)
    from felis.learning.landing.policy import load_policy

    behaviour, _ = load_policy(shipped_policy() if policy == "shipped" else policy)
    return LandingController(behaviour, drop_height=drop.height_m if drop else None)


@dataclass
class LandingOutcome:
    drop: Drop
    policy: str
    landed: bool
    foot_only: bool  # only feet on the floor from touchdown to touchdown + 0.5 s
    touchdown_s: float | None  # time from release to the first floor contact
    first_body: str | None  # a body that made that contact
    touch_body: str | None  # the first non-foot body on the floor within the window
    touch_s: float | None  # … how long after touchdown
    tilt_deg: float | None  # at touchdown + 0.5 s
    waist_m: float | None  # at touchdown + 0.5 s
    peak_impact: float  # peak ground reaction force, body weights
    final_tilt_deg: float  # at the end of the run
    why: str  # why it did not land ("" when it did)
    reasons: tuple[str, ...]  # the same as kinds fit for counting
    standing_waist_m: float

    def as_dict(self) -> dict:
        r = lambda v, n=4: None if v is None else round(float(v), n)  # noqa: E731
        return {**self.drop.as_dict(), "landed": self.landed, "why": self.why or None, "foot_only": self.foot_only,
                "touchdown_s": r(self.touchdown_s), "touch_body": self.touch_body, "touch_s": r(self.touch_s),
                "tilt_deg": r(self.tilt_deg, 2), "waist_m": r(self.waist_m), "peak_impact": r(self.peak_impact, 2),
                "final_tilt_deg": r(self.final_tilt_deg, 2)}


def standing_waist_height(robot: MujocoRobot, settle_s: float = 1.5) -> float:
    """Waist (``State.height``) of the cat at rest in its ``stand`` pose on the floor (m).

    Resets the robot, poses it, sets it down with its feet 1 mm up and lets it settle under the
    ``stand`` controller for ``settle_s``; leaves the robot armed, ready for `MujocoRobot.reset`.
    """
    robot.reset()
    set_pose(robot, robot.spec.pose("stand"))
    apply_drop(robot, Drop(0.0, 0.0, 0.0, 0.001))
    report = run_loop(robot, make_controller("stand"), duration=settle_s, keep_armed=True).raise_if_interrupted()
    height = report.final_state.height if report.final_state is not None else None
    if height is None:
        raise ParameterError(f"{robot.spec.name} has no waist height sensor (sensors.height)")
    return float(height)


class LandingSim:
    """A reusable simulated cat for drop episodes (one compiled model, reset between drops); measures the
    standing waist height once at construction."""

    def __init__(self, robot: str = "cat", design: str | None = None):
        """``design``: a cat of `felis.learning.landing.designs.DESIGNS` instead of the described one (its servos,
        paws and physics step), e.g. ``4ms-paw`` to replay what was recorded on the cat as described until
        2026-11-29."""
        self.spec = load_spec(robot)
        servo = edit = step = None
        if design is not None:
            from felis.learning.landing.designs import design_robot, get_design

            d = get_design(design)
            self.spec, servo, edit = design_robot(d, self.spec)
            step = d.timestep_s
        self.feet = tuple(self.spec.sensors.contacts)
        if not self.feet:
            raise ParameterError(f"{self.spec.name} has no foot contacts (sensors.contacts): it cannot be judged")
        self.robot = MujocoRobot(self.spec, servo=servo, edit=edit)
        self.robot.connect()
        if step is not None:
            self.robot.model.opt.timestep = step
        self.standing_waist_m = standing_waist_height(self.robot)

    def run(self, d: Drop, policy: str | Controller = "passive", monitors=(), duration: float | None = None
            ) -> LandingOutcome:
        """One drop episode (module doc). ``policy``: a policy name, or a controller to run as it is (e.g. a
        `felis.controllers.landing.LandingController`); ``monitors``: extra loop monitors (a video recorder,
        a motion recorder); ``duration``: the run's length (default: the fall time + `MARGIN_S`)."""
        robot = self.robot
        controller = make_policy(policy, d) if isinstance(policy, str) else policy
        policy = policy if isinstance(policy, str) else getattr(policy, "name", type(policy).__name__)
        robot.reset()
        apply_drop(robot, d)
        recorder = LandingRecorder(robot, self.feet).attach()
        diverged = False
        try:
            run_loop(robot, controller, duration=d.fall_time + MARGIN_S if duration is None else duration,
                     rate_hz=RATE_HZ, monitors=monitors, keep_armed=True).raise_if_interrupted()
        except SimulationError:
            diverged = True
        finally:
            recorder.detach()
        v = landing_verdict(recorder.truth(self.standing_waist_m))
        if diverged:  # MuJoCo reset the data: nothing after this point is the drop's
            return LandingOutcome(d, policy, False, False, v.touchdown_t, v.first_body, v.touch_body,
                                  None, None, None, recorder.peak_impact, float("nan"), "physics diverged",
                                  ("physics diverged",), self.standing_waist_m)
        return LandingOutcome(
            d, policy, v.landed, v.foot_only, v.touchdown_t, v.first_body, v.touch_body,
            None if v.touch_t is None else v.touch_t - v.touchdown_t, v.tilt_deg, v.waist_m,
            recorder.peak_impact, tilt_from_up(float(robot.data.xmat[robot.root_body, 8])), v.why,
            tuple(kind for kind, _ in v.reasons), self.standing_waist_m)

    def close(self) -> None:
        self.robot.close()


# ----------------------------------------------------------------------------------- parallel runs
_SIM: LandingSim | None = None


def _init(robot: str) -> None:
    """Per worker process: its own model."""
    global _SIM
    _SIM = LandingSim(robot)


def _one(args) -> LandingOutcome:
    d, policy = args
    return _SIM.run(d, policy)


def run_drops(drops: Sequence[Drop], policy: str = "passive", *, workers: int | None = None, robot: str = "cat",
              progress: Callable[[int], None] | None = None, chunk: int = 256,
              design: str = "cat", timestep: float | None = None) -> list[LandingOutcome]:
    """Run every drop with ``policy``, batched (`BatchLandingSim`: ``chunk`` cats at a time on ``workers``
    threads, default every core); results in drop order, identical whatever the number of workers (each cat
    is stepped alone). ``progress(n)`` after each batch of n drops. ``design``: another buildable cat
    (`felis.learning.landing.designs.DESIGNS`); ``timestep``: the physics step in s (default the design's;
    it must divide the 10 ms control tick)."""
    from felis.learning.landing.designs import design_sim, get_design

    check_policy(policy)  # a bad policy fails here, once, as one line
    get_design(design)
    if timestep is not None:
        check_timestep_ms(timestep * 1000.0)
    if workers is not None and workers < 1:
        raise ParameterError(f"workers must be ≥ 1, got {workers}")
    if not drops:
        return []
    sim = (BatchLandingSim(robot, nthread=workers, timestep=timestep) if design == "cat"
           else design_sim(design, nthread=workers, timestep=timestep))
    try:
        out: list[LandingOutcome] = []
        for i in range(0, len(drops), chunk):
            part = list(drops[i:i + chunk])
            out += sim.run(part, batch_controller(sim.spec, policy, part), policy=policy)
            if progress is not None:
                progress(len(part))
        return out
    finally:
        sim.close()


def run_drops_sequential(drops: Sequence[Drop], policy: str = "passive", *, workers: int | None = None,
                         robot: str = "cat", progress: Callable[[int], None] | None = None) -> list[LandingOutcome]:
    """The sequential path: each drop through `felis.loop.run_loop` (`LandingSim`), in a process pool of
    ``workers``; what `run_drops` is checked against (``tests/sim/test_batch.py``)."""
    check_policy(policy)
    if workers is not None and workers < 1:
        raise ParameterError(f"workers must be ≥ 1, got {workers}")
    if not drops:
        return []
    workers = worker_count(workers, len(drops))
    jobs = [(d, policy) for d in drops]
    if workers == 1:  # this process's own model, closed when done
        sim = LandingSim(robot)
        try:
            return run_jobs(lambda job: sim.run(*job), jobs, 1, progress=progress)
        finally:
            sim.close()
    return run_jobs(_one, jobs, workers, _init, (robot,), max(1, min(4, len(jobs) // (4 * workers))), progress)


# ----------------------------------------------------------------------------------- batched runs
def batch_controller(spec, policy: str, drops: Sequence[Drop]):
    """The batched controller (`felis.sim.batch.DropBatch`) for a checked policy name over ``drops``."""
    from felis.controllers.landing import LandingBatch, PerCat

    if policy in POLICIES or policy == "rules":
        return PerCat(spec, lambda b: make_policy(policy, drops[b]))
    n_ticks = max(int(round((d.fall_time + MARGIN_S) * RATE_HZ)) for d in drops)
    if policy == "caps+library":
        from felis.learning.landing.by_height import caps_library_batch
        from felis.learning.landing.designs import joint_speeds
        from felis.learning.landing.library import load_library

        return LandingBatch(spec, [caps_library_batch(caps_path("caps"), load_library(), [d.height_m for d in drops],
                                                      n_ticks, joint_speeds(spec))])
    vote = vote_path(policy)
    if vote is not None:
        from felis.learning.landing.by_attitude import vote_batch
        from felis.learning.landing.designs import joint_speeds
        from felis.learning.landing.library import load_library

        return LandingBatch(spec, [vote_batch(vote, load_library(), [d.height_m for d in drops], n_ticks,
                                              joint_speeds(spec))])
    caps = caps_path(policy)
    if caps is not None:
        from felis.learning.landing.cap_policy import load_cap_policy

        return LandingBatch(spec, [load_cap_policy(caps)])
    lib = library_path(policy)
    if lib is not None:
        from felis.learning.landing.designs import joint_speeds
        from felis.learning.landing.library import LibraryBatch, load_library

        return LandingBatch(spec, [LibraryBatch(load_library(lib), [d.height_m for d in drops], n_ticks,
                                                joint_speeds(spec))])
    from felis.learning.landing.policy import load_policy

    behaviour, _ = load_policy(shipped_policy() if policy == "shipped" else policy)
    return LandingBatch(spec, [behaviour])


def outcome_of(d: Drop, policy: str, r, standing_waist_m: float) -> LandingOutcome:
    """A `LandingOutcome` from one cat of a batch (`felis.sim.batch.BatchResult`), by the one verdict."""
    v = landing_verdict(r.truth)
    if r.diverged:
        return LandingOutcome(d, policy, False, False, v.touchdown_t, v.first_body, v.touch_body, None, None, None,
                              r.peak_impact, float("nan"), "physics diverged", ("physics diverged",), standing_waist_m)
    return LandingOutcome(
        d, policy, v.landed, v.foot_only, v.touchdown_t, v.first_body, v.touch_body,
        None if v.touch_t is None else v.touch_t - v.touchdown_t, v.tilt_deg, v.waist_m, r.peak_impact,
        tilt_from_up(r.final_up_z), v.why, tuple(kind for kind, _ in v.reasons), standing_waist_m)


class BatchLandingSim:
    """Drops in batches (`felis.sim.batch.DropBatch`, every core by default): what `run_drops`, training and
    the optimum use. The standing waist height is measured once, as `LandingSim` does."""

    def __init__(self, robot: str = "cat", *, nthread: int | None = None, servo=None, spec=None, sensors=None,
                 timestep: float | None = None):
        from felis.sim.batch import DropBatch

        self.spec = spec or load_spec(robot)
        self.batch = DropBatch(self.spec, servo=servo, nthread=nthread, sensors=sensors, timestep=timestep)
        self.standing_waist_m = standing_waist_height(self.batch.robot)

    def run(self, drops: Sequence[Drop], controller, *, policy: str = "", **kw) -> list[LandingOutcome]:
        results = self.batch.run(drops, controller, self.standing_waist_m, rate_hz=RATE_HZ, margin_s=MARGIN_S, **kw)
        return [outcome_of(d, policy, r, self.standing_waist_m) for d, r in zip(drops, results, strict=True)]

    def close(self) -> None:
        self.batch.close()


TILT_BINS = (0, 30, 60, 90, 120, 150, 180)


def by_tilt(drops: Sequence[Drop], landed: Sequence[bool]) -> dict[str, dict[str, int]]:
    """Landed / total per 30° bin of start tilt (the angle of the body's up-axis from vertical at release)."""
    from felis.rotations import euler_quat, tilt_deg

    out = {f"{a}-{b}": {"landed": 0, "total": 0} for a, b in zip(TILT_BINS, TILT_BINS[1:], strict=False)}
    keys = list(out)
    for d, ok in zip(drops, landed, strict=True):
        t = float(tilt_deg(euler_quat(d.roll_deg, d.pitch_deg, d.yaw_deg)))
        k = keys[min(len(keys) - 1, int(t // 30))]
        out[k]["total"] += 1
        out[k]["landed"] += int(bool(ok))
    return out


def summarise(outcomes: Sequence[LandingOutcome]) -> dict:
    """success_rate (landed / drops), counts, the reasons for the failures, and one entry per drop."""
    good = [o for o in outcomes if o.landed]
    reasons: dict[str, int] = {}
    for o in outcomes:
        for k in o.reasons:
            reasons[k] = reasons.get(k, 0) + 1
    return {
        "success_rate": round(len(good) / len(outcomes), 4) if outcomes else None,
        "landed": len(good), "total": len(outcomes),
        "reasons": dict(sorted(reasons.items(), key=lambda kv: (-kv[1], kv[0]))),
        "standing_waist_m": round(outcomes[0].standing_waist_m, 4) if outcomes else None,
        "drops": [o.as_dict() for o in outcomes],
    }
