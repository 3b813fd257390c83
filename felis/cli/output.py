"""Everything the ``felis`` command prints goes through here: the console, JSON, progress bars, errors.

One place so every command looks and behaves the same: a rich `console` without highlighting (colour
only where a message asks for it), JSON indented by `JSON_INDENT` (2) on standard output, progress bars
built by `bar` on rich.progress (off with ``--json`` or when the stream is not a terminal; the training
and evaluation commands then print a plain line per 10 % where they always have), and errors as one
line, ``error: …``, on standard error. No other CLI module creates a console or prints JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from felis.errors import ParameterError
from felis.files import check_target, write_atomic

if TYPE_CHECKING:  # rich loads when a command prints
    from rich.console import Console
    from rich.progress import Progress

JSON_INDENT = 2
EXIT_ERROR, EXIT_USAGE = 1, 2  # exit codes besides 0 and felis.shutdown.EXIT_INTERRUPTED (130)


# --------------------------------------------------------------------------------- text and JSON
def console(width: int | None = None) -> Console:
    """The console commands print through: no automatic highlighting, long lines not wrapped."""
    from rich.console import Console
    if width is None:
        return Console(highlight=False, soft_wrap=True)
    return Console(highlight=False, soft_wrap=True, width=width)


def dumps(obj, default=str) -> str:
    """``obj`` as the CLI's JSON text (values JSON lacks go through ``default``, text by default)."""
    return json.dumps(obj, indent=JSON_INDENT, default=default)


def print_json(obj, default=str) -> None:
    """Print ``obj`` as JSON on standard output."""
    print(dumps(obj, default))


def out(args, obj, human=None, *, rich: bool = False) -> None:
    """A command's result: JSON with ``--json``, else ``human`` when given: plain text, or through the
    console with ``rich`` (markup) or when it is a rich renderable (a table)."""
    if args.json:
        print_json(obj)
    elif isinstance(human, str) and not rich:
        print(human)
    elif human is not None:
        console().print(human)


def error(message: str) -> None:
    """One line on standard error: ``error: message``."""
    print(f"error: {message}", file=sys.stderr)


def live(url: str) -> None:
    """One line on standard error when a live view listens (stdout stays the command's result)."""
    print(f"live: {url} (Foxglove: Open connection → Foxglove WebSocket → {url})", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------- progress
def bar(*, quiet: bool, counts: bool = True, field: str | None = None, remaining: bool = True,
        transient: bool = True) -> Progress:
    """A rich progress display: description, bar, [done/total], [a task field], elapsed, [remaining].

    ``quiet`` turns it off (``--json``, or no terminal to draw on)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    columns = [TextColumn("{task.description}"), BarColumn()]
    if counts:
        columns.append(TextColumn("{task.completed}/{task.total}"))
    if field is not None:
        columns.append(TextColumn("{task.fields[" + field + "]}"))
    columns.append(TimeElapsedColumn())
    if remaining:
        columns.append(TimeRemainingColumn())
    return Progress(*columns, disable=quiet, transient=transient)


def progress(total: int, label: str, quiet: bool, lines: bool = False):
    """A progress bar over ``total`` items and its ``step(n)``; with ``lines`` (no terminal, not --json)
    ``step`` also prints a line per 10 %. Use the bar as a context manager."""
    b = bar(quiet=quiet)
    task = b.add_task(label, total=total)
    done = [0, 0]

    def step(n: int) -> None:
        b.update(task, advance=n)
        done[0] += n
        tenth = done[0] * 10 // max(total, 1)
        if lines and tenth > done[1]:
            done[1] = tenth
            print(f"{label}: {done[0]}/{total}", flush=True)

    return b, step


class LoopProgress:
    """A loop monitor (`felis.loop.run_loop`): a bar over the run's time, on a terminal only."""

    def __init__(self, label: str, duration: float):
        self.enabled = sys.stderr.isatty()
        self.duration = duration
        self._bar = bar(quiet=not self.enabled, counts=False, field="t", remaining=False)
        self._task = self._bar.add_task(label, total=duration, t="")
        self._t0 = None

    def reset(self, spec, state) -> None:
        self._t0 = state.t
        self._bar.start()

    def __call__(self, state, command) -> None:
        t = state.t - (self._t0 or 0.0)
        self._bar.update(self._task, completed=t, t=f"t={t:.2f} s")

    def stop(self) -> None:
        self._bar.stop()


class StageProgress:
    """A bar over a fraction 0…1 whose label changes by stage (``felis sysid``: recording, fitting)."""

    def __init__(self, enabled: bool):
        self.enabled = enabled and sys.stderr.isatty()
        self._bar = None
        if self.enabled:
            self._bar = bar(quiet=False, counts=False, remaining=False)
            self._task = self._bar.add_task("", total=1.0)
            self._bar.start()

    def __call__(self, description: str, fraction: float) -> None:
        if self._bar is not None:
            self._bar.update(self._task, description=description, completed=fraction)

    def stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()


# --------------------------------------------------------------------------------- result files
def check_json_out(path: Path | None) -> None:
    """Refuse a ``--out`` result file that is not ``.json`` or cannot be written, before any work."""
    if path is None:
        return
    if Path(path).suffix.lower() != ".json":
        raise ParameterError(f"{path}: the result file must end in .json")
    check_target(Path(path), "result", ParameterError)


def write_json_out(path: Path | None, result: dict) -> None:
    """Write ``--out`` atomically (nothing when None)."""
    if path is not None:
        write_atomic(path, dumps(result) + "\n", "result", ParameterError)


def emit(args, result: dict, print_summary) -> int:
    """The end of an eval command: ``--out`` written, then JSON (``--json``) or the text summary."""
    write_json_out(args.out, result)
    if args.json:
        print_json(result)
    else:
        print_summary(result)
    return 0
