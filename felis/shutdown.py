"""One shutdown path: SIGINT, SIGTERM and SIGHUP all become `Interrupted` in the main thread.

Every command that can power servos already turns torque off, reads it back, writes its log's summary
and stops its children when a ``KeyboardInterrupt`` unwinds it (`felis.loop.run_loop`, the robots'
context managers, `felis.drivers.virtual.spawn`). Python raises ``KeyboardInterrupt`` for SIGINT only;
SIGTERM (``kill``, systemd, a CI runner's time-out) and SIGHUP (the terminal closed, a tmux session
killed, an SSH link dropped) would end the process at once and leave the servos powered. `signals`
routes all three through the same exception, so there is one way out whatever stops a command.

Rules:

* The first signal raises `Interrupted` (a ``KeyboardInterrupt``) in the main thread, naming the
  signal: ``stopped: interrupted (SIGTERM)``.
* Later signals while the command is unwinding are noted and do not raise: a second Ctrl-C must not
  cut the torque-off write in half. SIGKILL cannot be caught: that is what the servos' Bus Watchdog
  is for (`felis.drivers.dynamixel.robot`).
* The exit code of an interrupted command is 130 (`EXIT_INTERRUPTED`), whichever signal it was.
* Python ignores an exception raised inside a finaliser (``__del__``, a weakref callback): a signal whose
  handler runs there would be lost. The signals are counted (`count`), and `felis.loop.run_loop` raises
  `Interrupted` at its next tick for one that arrived during the run but did not stop it.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
SIGNALS = tuple(s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s is not None)


class Interrupted(KeyboardInterrupt):
    """A command was stopped by a signal (SIGINT, SIGTERM or SIGHUP)."""

    def __init__(self, signame: str = "SIGINT"):
        super().__init__(signame)
        self.signame = signame


class _State:
    def __init__(self):
        self.received: list[str] = []


_state = _State()


def received() -> list[str]:
    """The signals received since `signals` was entered (names), first first."""
    return list(_state.received)


def count() -> int:
    """How many signals `signals` has received since it was entered (0 outside it)."""
    return len(_state.received)


def signal_name(exc: BaseException | None) -> str:
    """``"SIGTERM"`` for an `Interrupted` by SIGTERM, ``"SIGINT"`` for a plain Ctrl-C."""
    return getattr(exc, "signame", "SIGINT")


def _handler(signum, frame) -> None:
    name = signal.Signals(signum).name
    _state.received.append(name)
    if len(_state.received) == 1:
        raise Interrupted(name)
    # already unwinding: let the torque-off, the log summary and the children's stop finish


@contextlib.contextmanager
def signals(which: tuple[int, ...] = SIGNALS) -> Iterator[None]:
    """Route SIGINT, SIGTERM and SIGHUP (or ``which`` of them) to `Interrupted` (main thread only; elsewhere a
    no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state.received = []
    previous = {}
    for s in which:
        with contextlib.suppress(OSError, ValueError):
            previous[s] = signal.signal(s, _handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            with contextlib.suppress(OSError, ValueError):
                signal.signal(s, h)


def is_interrupted(stopped: str) -> bool:
    """Whether a loop report's ``stopped`` says a signal ended the run."""
    return stopped.startswith("interrupted")
