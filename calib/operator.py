"""The operator at the bench: what calibration asks of a person, and who answers.

Calibration steps need hands: connect one servo, put the robot in its reference pose, sweep a
joint. The steps talk to an `Operator`, never to the terminal, so the same code runs:

* interactively (`ConsoleOperator`: prompts on the terminal, Enter to go on, a live table while
  sweeping);
* unattended (`ConsoleOperator(yes=True)`: prints each instruction and goes on at once; a sweep
  lasts ``sweep_s`` seconds while a script or a person moves the joints);
* from a calibration script (`ScriptedOperator`: Python callbacks do what the hands would).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from felis.errors import CalibrationError


@dataclass
class SweepRow:
    """One joint's live sweep readout (ticks; degrees for people)."""

    joint: str
    servo_id: int
    lo: int
    position: int
    hi: int
    seam: bool = False  # the readings wrapped across 0/4095


class Operator(Protocol):
    def say(self, message: str) -> None:
        """Information; no answer expected."""

    def wait(self, message: str) -> None:
        """An instruction; returns when the operator has done it."""

    def confirm(self, message: str) -> bool:
        """A yes/no question before something irreversible."""

    def sweep(self, instruction: str, update: Callable[[], list[SweepRow]]) -> None:
        """Call ``update()`` repeatedly (≈ 20 Hz) while the joints are swept; return when done."""


class ConsoleOperator:
    """Terminal prompts (``input``) and a rich live table; ``yes`` answers every prompt at once."""

    def __init__(self, *, yes: bool = False, sweep_s: float = 10.0, quiet: bool = False, stream=None):
        from rich.console import Console

        self.yes = yes
        self.sweep_s = sweep_s
        self.quiet = quiet
        self.console = Console(file=stream or (sys.stderr if quiet else sys.stdout), highlight=False, soft_wrap=True)

    def say(self, message: str) -> None:
        self.console.print(message)

    def wait(self, message: str) -> None:
        if self.yes:
            self.console.print(f"{message} [--yes: going on]")
            return
        self.console.print(f"{message} — press Enter when done")
        self._line()

    def confirm(self, message: str) -> bool:
        if self.yes:
            self.console.print(f"{message} [--yes]")
            return True
        self.console.print(f"{message} [y/N]")
        return self._line().strip().lower() in ("y", "yes")

    def _line(self) -> str:
        line = sys.stdin.readline()
        if not line:
            raise CalibrationError("no answer on standard input (closed); run with --yes for unattended use")
        return line

    def sweep(self, instruction: str, update: Callable[[], list[SweepRow]]) -> None:
        from rich.live import Live

        done = threading.Event()
        if self.yes:
            self.console.print(f"{instruction} [--yes: recording for {self.sweep_s:g} s]")
            deadline = time.monotonic() + self.sweep_s
        else:
            self.console.print(f"{instruction} — press Enter when every joint has been through its whole travel")
            deadline = float("inf")

            def reader():
                sys.stdin.readline()
                done.set()

            threading.Thread(target=reader, name="sweep-enter", daemon=True).start()
        rows = update()
        with Live(sweep_table(rows), console=self.console, refresh_per_second=10, transient=False) as live:
            while not done.is_set() and time.monotonic() < deadline:
                time.sleep(0.05)
                rows = update()
                live.update(sweep_table(rows))


def sweep_table(rows: list[SweepRow]):
    from rich.table import Table

    t = Table(title="sweep (degrees from the reference pose)")
    for col in ("joint", "ID", "min", "position", "max", ""):
        t.add_column(col, justify="right" if col in ("ID", "min", "position", "max") else "left")
    for r in rows:
        t.add_row(r.joint, str(r.servo_id), f"{_deg(r.lo):+.1f}", f"{_deg(r.position):+.1f}", f"{_deg(r.hi):+.1f}",
                  "[red]crossed 0/4095 seam[/]" if r.seam else "")
    return t


def _deg(tick: int) -> float:
    return (tick - 2048) * 360.0 / 4096


class ScriptedOperator:
    """An operator made of callbacks, for calibration scripts and tests.

    ``on_wait(message)`` runs for each instruction (e.g. plug the next servo in, pose the robot);
    ``on_sweep(k)`` runs before the k-th sweep poll and returns True when the sweep is over (default:
    ``sweep_polls`` polls). ``answers`` are returned by ``confirm`` in order (default: yes).
    ``log`` keeps every message.
    """

    def __init__(self, on_wait: Callable[[str], None] | None = None,
                 on_sweep: Callable[[int], bool] | None = None, *, sweep_polls: int = 20,
                 answers: list[bool] | None = None):
        self.on_wait, self.on_sweep, self.sweep_polls = on_wait, on_sweep, sweep_polls
        self.answers = list(answers) if answers is not None else None
        self.log: list[str] = []
        self.rows: list[SweepRow] = []

    def say(self, message: str) -> None:
        self.log.append(message)

    def wait(self, message: str) -> None:
        self.log.append(message)
        if self.on_wait is not None:
            self.on_wait(message)

    def confirm(self, message: str) -> bool:
        self.log.append(message)
        return self.answers.pop(0) if self.answers else self.answers is None

    def sweep(self, instruction: str, update: Callable[[], list[SweepRow]]) -> None:
        self.log.append(instruction)
        k = 0
        while True:
            if self.on_sweep is not None:
                if self.on_sweep(k):
                    break
            elif k >= self.sweep_polls:
                break
            self.rows = update()
            k += 1
        self.rows = update()
