"""One controller run for a test: `felis.loop.run_loop` with an MCAP run log, the log read back.

`run_controller` returns a `RunResult`: the loop's `LoopReport` and the log as `felis.logs.reader.LogData`
(what `read_log` gives: joint states and commands, events, the summary), so a test asserts on what the file
holds, as an engineer reading the log would (`felis.testing.assertions`). The clock follows the robot: a
simulation runs on simulated time (as fast as it steps), hardware and servo-in-the-loop on the wall clock.
Whatever ends the run, the log is closed: with the report as its summary, or ``{"error": "run aborted"}``
when an exception escapes (the loop has already turned torque off).
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from felis.errors import ParameterError
from felis.hal import Controller, Robot, State

if TYPE_CHECKING:
    from felis.logs.reader import LogData
    from felis.loop import LoopReport, Monitor
    from felis.safety import SafetyConfig


@dataclass
class RunResult:
    """What a run did (``report``) and what its log holds (``log``; None when run without one, ``path`` too)."""

    report: LoopReport
    log: LogData | None
    path: Path | None

    @property
    def ok(self) -> bool:
        return self.report.ok


def controller_from(controller: str | Controller, spec, **options) -> Controller:
    """A controller object as given, or one built by name (`felis.controllers.make_controller` with ``options``);
    one that needs the robot's body model (the balance monitor) gets it from the MJCF, as ``felis run`` does."""
    if not isinstance(controller, str):
        if options:
            raise ParameterError(f"controller options ({', '.join(sorted(options))}) go with a controller name, "
                                 "not a controller object")
        return controller
    from felis.controllers import CONTROLLERS, make_controller

    factory = CONTROLLERS.get(controller)
    if factory is not None and "body" in inspect.signature(factory).parameters and "body" not in options:
        from felis.sim.bodymodel import load_body_model  # late: MuJoCo

        options["body"] = load_body_model(spec)
    return make_controller(controller, **options)


def run_controller(robot: Robot, controller: str | Controller, seconds: float, *, log: str | Path | None = None,
                   rate: float | None = None, clock: str | None = None, safety: SafetyConfig | None = None,
                   monitors: Iterable[Monitor] = (), until: Callable[[State], bool] | None = None,
                   meta: dict | None = None, **options) -> RunResult:
    """Run ``controller`` (an object, or a name such as ``"stand"`` with its ``options``) on the connected
    ``robot`` for ``seconds`` at ``rate`` Hz (default: the description's), logging to ``log`` (an ``.mcap`` path;
    None: no log). ``clock`` defaults to ``"wall"`` for a real-time robot (servos, virtual or not) and ``"sim"``
    otherwise; ``safety``, ``monitors`` and ``until`` go to `run_loop`. The robot is armed by the loop and
    disarmed at the end."""
    import signal

    from felis.loop import run_loop
    from felis.shutdown import signals

    ctl = controller_from(controller, robot.spec, **options)
    clock = clock or ("wall" if robot.realtime else "sim")
    runlog = None
    if log is not None:
        from felis.logs.runlog import RunLog  # late: the Foxglove SDK

        name = getattr(ctl, "name", type(ctl).__name__)
        runlog = RunLog(log, robot.spec, {"controller": str(name), "backend": "dxl" if robot.realtime else "sim",
                                          "test": True, **(meta or {})})
    try:
        # Ctrl-C through felis's handler (SIGTERM keeps its default): counted, so a run stops on it even when
        # Python loses the KeyboardInterrupt in a finaliser (`felis.shutdown`)
        with signals((signal.SIGINT,)):
            report = run_loop(robot, ctl, duration=seconds, rate_hz=rate, clock=clock, safety=safety, log=runlog,
                              monitors=monitors, until=until)
    except BaseException:
        if runlog is not None:
            with contextlib.suppress(Exception):  # the run's own exception is the one to report
                runlog.close({"error": "run aborted"})
        raise
    if runlog is None:
        return RunResult(report, None, None)
    runlog.close({"run": report.as_dict()})
    from felis.logs.reader import read_log

    return RunResult(report, read_log(log), Path(log))
