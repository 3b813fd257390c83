"""Shared pieces of the evaluation and training commands: progress bars and JSON result files."""

from __future__ import annotations

import json
from pathlib import Path

from felis.errors import ParameterError


def progress(total: int, label: str, quiet: bool, lines: bool = False):
    """A rich progress bar on a terminal; with ``lines`` (no terminal, not --json) a line per 10 %."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                   TimeElapsedColumn(), TimeRemainingColumn(), disable=quiet, transient=True)
    task = bar.add_task(label, total=total)
    done = [0, 0]

    def step(n: int) -> None:
        bar.update(task, advance=n)
        done[0] += n
        tenth = done[0] * 10 // max(total, 1)
        if lines and tenth > done[1]:
            done[1] = tenth
            print(f"{label}: {done[0]}/{total}", flush=True)

    return bar, step


def check_json_out(path: Path | None) -> None:
    """Refuse a ``--out`` result file that is not ``.json`` or cannot be written, before any work."""
    if path is None:
        return
    from felis.files import check_target

    if Path(path).suffix.lower() != ".json":
        raise ParameterError(f"{path}: the result file must end in .json")
    check_target(Path(path), "result", ParameterError)


def write_json_out(path: Path | None, result: dict) -> None:
    """Write ``--out`` atomically (nothing when None)."""
    if path is not None:
        from felis.files import write_atomic

        write_atomic(path, json.dumps(result, indent=1) + "\n", "result", ParameterError)


def emit(args, result: dict, print_summary) -> int:
    """The end of an eval command: ``--out`` written, then JSON (``--json``) or the text summary."""
    write_json_out(args.out, result)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print_summary(result)
    return 0
