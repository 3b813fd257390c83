"""A log's deferred writes run on a thread of their own, in slices, while the control loop's thread is inside C
code that releases the interpreter lock: the physics step (``mujoco.mj_step``), a sleep until the next tick, a
read from the bus.

Why: a run log encodes and writes a chunk's messages at once (`felis.logs.runlog`, "Speed"); done on the loop's
thread, that work (about 35 µs a tick for the cat's full log) adds to every tick. Python runs one thread at a time,
but ``mj_step`` of ten physics steps lets go of the interpreter for ~0.25 ms a tick, and a second core can encode
and write then. The catch is coming back: when the loop's thread returns from C code it must wait until the writer
lets go of the interpreter, which an unprompted thread does only every ``sys.getswitchinterval()`` (5 ms by
default). So the writer works in *slices*, starts only when the loop nudges it (`Background.nudge`, once a tick,
just before the physics step or the sleep), and stops after a time budget: the budget grows while the writer is
never kept waiting, and shrinks whenever it finds it was (its wall time ran ahead of its own CPU time: the loop
took the interpreter back). While a writer exists the switch interval is at most `SWITCH_S`, so a writer that
overruns keeps the loop waiting that long at most.

The order of writes is kept: jobs (iterators; each ``next`` is one slice) run one after another, and the loop's
thread runs whatever is left itself (`Background.drain`) before it hands over the next chunk (so at most one
handed-over chunk is ever unwritten: the crash bound in `felis.logs.mcap`), flushes or closes. An error in a job
stops the writer; the loop's thread raises it at its next call (`Background.check`).
"""

from __future__ import annotations

import _thread
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator

SWITCH_S = 2e-4  # the interpreter's switch interval while a writer exists (seconds; CPython's default is 5e-3)
BUDGET_S = (2e-5, 1e-4, 5e-3)  # a slice's time budget: least, first, most
PREEMPTED_S = 2e-5  # wall time beyond the writer's own CPU time that means it was kept off the interpreter

_active = 0  # writers alive (the switch interval is lowered while any is)
_saved_interval: float | None = None
_count_lock = threading.Lock()


def _enter() -> None:
    global _active, _saved_interval
    with _count_lock:
        if _active == 0:
            _saved_interval = sys.getswitchinterval()
            if _saved_interval > SWITCH_S:
                sys.setswitchinterval(SWITCH_S)
        _active += 1


def _leave() -> None:
    global _active, _saved_interval
    with _count_lock:
        _active -= 1
        if _active == 0 and _saved_interval is not None:
            if abs(sys.getswitchinterval() - SWITCH_S) < 1e-9:  # not changed by someone else since (stored in µs)
                sys.setswitchinterval(_saved_interval)
            _saved_interval = None


class Background:
    """A writer thread for one log. ``submit(job)`` queues an iterator of slices; ``nudge()`` lets the writer run
    a budget's worth of slices; ``drain()`` runs what is left on the calling thread; ``close()`` drains and ends
    the thread. Not for use from several threads but the writer's own and one caller's."""

    def __init__(self, name: str = "felis-log-writer"):
        self._jobs: deque[Iterator] = deque()
        self._go = _thread.allocate_lock()
        self._go.acquire()  # released by `nudge`, taken by the writer
        self._run = threading.Lock()  # held while slices run (writer or `drain`)
        self._stop = False
        self.error: BaseException | None = None
        self.budget = BUDGET_S[1]
        self.slices = self.preempted = 0  # statistics: slices the writer ran, sessions cut short by the loop
        _enter()
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self._thread.start()

    @property
    def pending(self) -> bool:
        """Jobs not finished yet."""
        return bool(self._jobs)

    def submit(self, job: Iterator) -> None:
        self._jobs.append(job)

    def nudge(self) -> None:
        """Let the writer run a slice budget now (call just before the loop waits in C code); no effect when
        there is nothing to do or it is already running."""
        if self._jobs and self._go.locked():
            self._go.release()

    def _main(self) -> None:
        while True:
            self._go.acquire()
            if self._stop:
                return
            self._session()

    def _session(self) -> None:
        wall0, cpu0 = time.perf_counter(), time.thread_time()
        budget = self.budget
        ran_out = False
        with self._run:
            jobs = self._jobs
            while jobs and not self._stop and self.error is None:
                try:
                    next(jobs[0])
                except StopIteration:
                    jobs.popleft()
                except BaseException as e:  # noqa: BLE001 - handed to the loop's thread (`check`)
                    self.error = e
                    jobs.clear()
                    return
                self.slices += 1
                wall = time.perf_counter() - wall0
                if wall - (time.thread_time() - cpu0) > PREEMPTED_S:  # the loop took the interpreter back
                    self.preempted += 1
                    self.budget = max(BUDGET_S[0], 0.7 * budget)
                    return
                if wall > budget:
                    ran_out = True
                    break
        if ran_out and jobs:
            self.budget = min(BUDGET_S[2], 1.25 * budget)

    def check(self) -> None:
        """Raise the error a job raised on the writer (once)."""
        e = self.error
        if e is not None:
            self.error = None
            raise e

    def drain(self) -> None:
        """Run every queued job to its end on this thread (after the writer's running slice), then `check`."""
        with self._run:
            jobs = self._jobs
            while jobs and self.error is None:
                try:
                    for _ in jobs[0]:
                        pass
                except BaseException as e:  # noqa: BLE001 - raised below, as the writer's would be
                    self.error = e
                    jobs.clear()
                    break
                jobs.popleft()
        self.check()

    def abandon(self) -> None:
        """End the writer without writing what is queued: its log was dropped without `close` (a weak finalizer
        calls this, from whichever thread collects the log; it does not wait for the thread)."""
        if self._stop:
            return
        self._stop = True
        self._jobs.clear()
        if self._go.locked():
            self._go.release()
        _leave()

    def close(self) -> None:
        """`drain`, then end the writer thread. Idempotent; the error of a job is raised after the thread ended."""
        try:
            if not self._stop:
                self.drain()
        finally:
            if not self._stop:
                self._stop = True
                if self._go.locked():
                    self._go.release()
                self._thread.join()
                _leave()
