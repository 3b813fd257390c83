"""``--live [HOST:]PORT`` on ``felis eval balance`` and ``felis eval landing``: the evaluation's one episode served
to Foxglove over the Foxglove WebSocket protocol while it runs (`felis.logs.live`, the same channels as a run
log: joint states and commands, every body's transform, the /robot scene, IMU, contacts, events, and the
skill's own: ``/balance``, ``/phase``, ``/landing``).

A viewer follows one robot: ``--live`` with more than one episode (pushes, drops) is refused in one line; pick
the one to watch (``random:1 --seed S``, or a file with one entry). That episode runs in this process on the
evaluation's sequential path (`felis.learning.balance.evaluate.PushSim`, `felis.learning.landing.evaluate.
LandingSim`: the episode functions its workers run, so the verdict is the evaluation's), paced to the wall clock
(`Pacer`) so the viewer shows it at its real speed.
"""

from __future__ import annotations

import time

from felis.cli import output
from felis.errors import ParameterError


def check_one(args, n: int, what: str) -> bool:
    """True when ``--live`` is given (and ``n`` is 1); a one-line error for ``--live`` with ``n`` ≠ 1."""
    if getattr(args, "live", None) is None:
        return False
    if n != 1:
        raise ParameterError(f"--live shows one episode, and {n} {what} are given: choose one (e.g. random:1 with "
                             "--seed S, or a file with one entry)")
    from felis.logs.live import parse_address

    parse_address(args.live)
    return True


class Pacer:
    """Loop monitor: sleeps so that run time keeps pace with the wall clock (a simulated episode shown live)."""

    def __init__(self):
        self._t0: float | None = None

    def reset(self, spec=None, state=None) -> None:
        self._t0 = None

    def __call__(self, state, command=None) -> None:
        now = time.perf_counter()
        if self._t0 is None:
            self._t0 = now - state.t
            return
        wait = self._t0 + state.t - now
        if wait > 0:
            time.sleep(wait)


class LogMonitor:
    """Loop monitor writing each tick's state and sent command to a run log: the log of an episode whose runner
    takes monitors but no log (`felis.learning.landing.evaluate.LandingSim`)."""

    def __init__(self, log):
        self.log = log

    def reset(self, spec=None, state=None) -> None:
        if state is not None:
            self.log.event(state.t, "armed")

    def __call__(self, state, command) -> None:
        self.log.state(state)
        self.log.command(state.t, command)


class LiveEpisode:
    """The live view and the run log (no file) of one episode: ``with LiveEpisode(args.live, spec, meta, robot)
    as log:`` … ``log.close(summary)``. ``robot``: a `felis.sim.MujocoRobot` (MuJoCo's scene and poses), or None
    for a robot on servos (the body model's: `felis.sim.scene.hardware_view`)."""

    def __init__(self, address: str, spec, meta: dict, robot=None):
        self.address, self.spec, self.meta, self.robot = address, spec, meta, robot
        self.view = self.log = None

    def __enter__(self):
        from felis.logs.live import LiveView
        from felis.logs.runlog import RunLog
        from felis.sim.scene import MujocoPoses, hardware_view, model_scene

        if self.robot is not None:
            scene, poses = model_scene(self.robot.model), MujocoPoses(self.robot)
        else:
            scene, poses = hardware_view(self.spec) or (None, None)
        self.view = LiveView(self.address)
        output.live(self.view.url)
        try:
            self.log = RunLog(None, self.spec, self.meta, scene=scene, poses=poses, live=self.view)
        except BaseException:
            self.view.close()
            raise
        return self.log

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if not self.log.closed:
                self.log.close({"error": "run aborted"} if exc_type is not None else None)
        finally:
            self.view.close()


def live_drop(address: str, drop, policy: str):
    """``felis eval landing --live``: one drop (`felis.scenarios.Drop`) with ``policy``, served live; its
    `felis.learning.landing.evaluate.LandingOutcome`, the verdict also on ``/landing``."""
    from felis.learning.landing.evaluate import LandingSim

    sim = LandingSim()
    try:
        meta = {"eval": "landing", "backend": "sim", "policy": policy, "drop": drop.as_dict()}
        with LiveEpisode(address, sim.spec, meta, sim.robot) as log:
            logger = LogMonitor(log)
            outcome = sim.run(drop, policy, monitors=[logger, Pacer()])
            verdict = outcome.as_dict()
            log.message("/landing", float(sim.robot.read().t), verdict)
            log.close({"landing": verdict})
    finally:
        sim.close()
    return outcome


def live_push(address: str, push, reaction: str, selector=None, backend: str = "sim"):
    """``felis eval balance --live``: one push (`felis.scenarios.Push`) with ``reaction`` (a name, or
    ``"selector"`` with ``selector`` a file or None for the shipped one), served live with ``/balance``; its
    `felis.learning.balance.evaluate.PushOutcome`. ``backend="dxl"``: through the virtual bus (wall clock)."""
    from felis.learning.balance.evaluate import PushSim, run_push_virtual

    react = reaction
    if reaction == "selector":
        from felis.controllers.reactions import FEATURES
        from felis.learning.balance.selector import load_selector

        react = load_selector(selector, feature_names=FEATURES)
    meta = {"eval": "balance", "backend": backend, "reaction": reaction, "push": push.as_dict()}
    if backend == "dxl":
        from felis.spec import load_spec

        with LiveEpisode(address, load_spec("cat"), meta) as log:
            outcome = run_push_virtual(push, react, log=log)
            outcome.reaction = reaction
            log.close({"push": outcome.as_dict()})
        return outcome
    sim = PushSim()
    try:
        with LiveEpisode(address, sim.spec, meta, sim.robot) as log:
            outcome = sim.run(push, react, monitors=[Pacer()], log=log)
            outcome.reaction = reaction
            log.close({"push": outcome.as_dict()})
    finally:
        sim.close()
    return outcome
