"""Output files: parent folders made with a clear error, permissions as a plain ``open`` gives, and
atomic replacement; and the bound on every user file felis reads whole (`check_readable`: a regular
file, no larger than its kind can be), so ``/dev/zero`` or a wrong multi-gigabyte file is one line, not
a process that grows until it is killed.

Every writer in felis (run logs, plots, videos, calibration and servo parameter files) prepares its
target here, so an operator who gives a bad path gets one line naming the part that is wrong; files
that must never be seen half-written (plots, calibration, servo parameters) go through `write_atomic`.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

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


def temp_beside(path: Path, content: bytes | Callable[[BinaryIO], None], what: str,
                error: type[FelisError] = FelisError) -> str:
    """A temporary file in ``path``'s folder holding ``content`` (bytes, or written by a callable given
    the open binary file), flushed and fsynced, with a normal file's mode; returns its name.

    The name is ``.<name>.<random>.tmp``: a write killed before its rename leaves only such a file.
    """
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise error(f"cannot write {what} {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(content):
                content(f)
            else:
                f.write(content)
            f.flush()
            os.fsync(f.fileno())
        default_mode(tmp)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise error(f"cannot write {what} {path}: {e.strerror or e}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


def write_atomic(path: str | Path, content: str | bytes | Callable[[BinaryIO], None], what: str,
                 error: type[FelisError] = FelisError, *, backup: Path | None = None) -> Path:
    """Replace ``path`` with ``content`` so that a reader, or a crash at any instant, sees either the old
    file or the new one whole: temporary file beside it (`temp_beside`), then ``os.replace``, then an
    fsync of the folder. With ``backup``, the current file is first copied there (atomically too).
    """
    path = Path(path)
    prepare_parent(path, what, error)
    data = content.encode("utf-8") if isinstance(content, str) else content
    tmp = temp_beside(path, data, what, error)
    try:
        if backup is not None and path.is_file():
            os.replace(temp_beside(backup, path.read_bytes(), what, error), backup)
        os.replace(tmp, path)
    except OSError as e:
        raise error(f"cannot write {what} {path}: {e.strerror or e}") from None
    finally:
        Path(tmp).unlink(missing_ok=True)
    sync_dir(path.parent)
    return path


def sync_dir(folder: Path) -> None:
    """fsync a folder so a rename in it survives a power cut (best effort)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


MAX_TEXT_BYTES = 16 * 2**20  # descriptions, calibration, servo parameters, trajectories, push and drop files
MAX_ARRAY_BYTES = 1 * 2**30  # .npz weights, recordings, datasets, checkpoints
MAX_LOG_BYTES = 4 * 2**30  # run logs


def check_readable(path: str | Path, what: str, error: type[FelisError] = FelisError,
                   limit: int = MAX_TEXT_BYTES) -> None:
    """Refuse, with one line, a user file felis would read whole that is not a regular file (``/dev/zero``,
    a FIFO, a terminal: endless) or is larger than any ``what`` can be. A missing file passes (the caller
    says "no such …" its own way)."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError:
        return
    import stat

    if stat.S_ISDIR(st.st_mode):
        return  # the caller's own "is a directory" line
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: not a regular file, so not a {what} (a device or a pipe would be read without end)")
    if st.st_size > limit:
        raise error(f"{path}: {st.st_size / 2**20:.0f} MiB is more than a {what} can be "
                    f"({limit / 2**20:.0f} MiB at most); is it the right file?")


def read_json(path: str | Path, what: str, error: type[FelisError] = FelisError, hint: str = "") -> object:
    """Parse the JSON file ``path`` (a ``what``: "push file", "drops file", …); a missing, unreadable or
    malformed file is one-line ``error`` naming it (``hint`` is added to "no such …", e.g. how to make one)."""
    path = Path(path)
    check_readable(path, what, error)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise error(f"{path}: no such {what}{hint}") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not a {what}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{path}: cannot read: {type(e).__name__}: {getattr(e, 'strerror', None) or e}") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: not JSON: {e.msg} at line {e.lineno} column {e.colno}") from None


def read_npz(path: str | Path, what: str, error: type[FelisError] = FelisError) -> dict:
    """All arrays of an ``.npz`` (``allow_pickle=False``); error with one line for a missing,
    unreadable, truncated or non-npz file, one holding pickled objects or a member that is not an array.
    ``what`` names the file kind ("weights", "selector", …), ``error`` the exception to raise."""
    import zipfile
    import zlib

    import numpy as np

    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such {what} file")
    if path.is_dir():
        raise error(f"{path}: is a directory, not a {what} file")
    check_readable(path, f"{what} file", error, MAX_ARRAY_BYTES)
    try:
        z = np.load(path, allow_pickle=False)
    except ValueError:  # neither zip nor .npy magic: numpy would have to unpickle it
        raise error(f"{path}: not a {what} file (.npz): neither an npz archive nor an array "
                           "(a pickle or a text file?)") from None
    except PermissionError:
        raise error(f"{path}: cannot read {what} file: permission denied") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise error(f"{path}: corrupt or truncated {what} file ({one_line(e)})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise error(f"{path}: a single .npy array, not a {what} file (.npz)")
    try:
        with z:
            data = {k: z[k] for k in z.files}
    except ValueError as e:
        if "Object arrays" in str(e) or "pickle" in str(e):
            raise error(f"{path}: holds pickled objects, which felis refuses to load") from None
        raise error(f"{path}: corrupt {what} file ({one_line(e)})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError) as e:
        raise error(f"{path}: corrupt or truncated {what} file ({one_line(e)})") from None
    odd = [k for k, v in data.items() if not isinstance(v, np.ndarray)]
    if odd:  # a zip member that is not a .npy array comes back as raw bytes
        raise error(f"{path}: member {odd[0]!r} is not an array; corrupt or not a {what} file")
    return data


def one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:200]}"


def check_fields(item: object, fields: tuple[str, ...], where: str, error: type[FelisError] = FelisError) -> dict:
    """``item`` as a JSON object with exactly ``fields``: one-line ``error`` naming ``where`` otherwise."""
    if not isinstance(item, dict):
        raise error(f"{where}: expected an object with {', '.join(fields)}, got {type(item).__name__}")
    missing = [k for k in fields if k not in item]
    if missing:
        raise error(f"{where}: missing {', '.join(missing)}")
    extra = sorted(set(item) - set(fields))
    if extra:
        raise error(f"{where}: unknown field {extra[0]!r} (fields: {', '.join(fields)})")
    return item


def finite_number(item: dict, key: str, where: str, error: type[FelisError] = FelisError) -> float:
    """``item[key]`` as a finite float (not a bool, not a string); one-line ``error`` otherwise."""
    import math

    v = item[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise error(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)
