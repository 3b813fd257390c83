"""Output files: parent folders made with a clear error, and permissions as a plain ``open`` gives.

Every writer in felis (run logs, plots, videos, later calibration files) prepares its target here,
so an operator who gives a bad path gets one line naming the part that is wrong.
"""

from __future__ import annotations

import os
from pathlib import Path

from felis.errors import FelisError


def check_target(path: Path, what: str, error: type[FelisError] = FelisError) -> None:
    """Raise ``error`` if ``path`` cannot be a file: a parent is a file, or it is a directory.

    Creates nothing, so a command can check all its outputs before writing any of them.
    """
    for parent in reversed(path.parents):
        if parent.exists() and not parent.is_dir():
            raise error(f"cannot write {what} {path}: {parent} is a file, not a directory")
    if path.is_dir():
        raise error(f"cannot write {what} {path}: it is a directory")


def prepare_parent(path: Path, what: str, error: type[FelisError] = FelisError) -> None:
    """Create ``path``'s parent folders; raise ``error`` naming the component that blocks it."""
    check_target(path, what, error)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise error(f"cannot write {what} {path}: {e.strerror or e}") from None


def default_mode(path: str | Path) -> None:
    """Give a temporary file (0600 from mkstemp) the mode a normal new file gets (0666 & ~umask)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)
