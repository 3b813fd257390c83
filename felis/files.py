"""Output files: parent folders made with a clear error, permissions as a plain ``open`` gives, and
atomic replacement; and the bound on every user file felis reads whole (`check_readable`: a regular
file, no larger than its kind can be), so ``/dev/zero`` or a wrong multi-gigabyte file is one line, not
a process that grows until it is killed.

Every writer in felis (run logs, plots, videos, calibration and servo parameter files) prepares its
target here, so an operator who gives a bad path gets one line naming the part that is wrong; files
that must never be seen half-written (plots, calibration, servo parameters) go through `write_atomic`.

And the readers every kind of user file shares, each fault one line of the caller's error class in the
caller's words: text (`read_text`), JSON (`read_json`, `read_json_list`, `check_fields`, `finite_number`,
`dataclass_from_json`) and ``.npz`` weights with their JSON metadata (`read_npz`, `read_meta`,
`check_float_arrays`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from collections.abc import Callable, Container, Mapping
from pathlib import Path
from typing import BinaryIO, TypeVar

from felis.errors import FelisError

T = TypeVar("T")


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


def read_text(path: str | Path, what: str, error: type[FelisError] = FelisError, *,
              hint: str | Callable[[], str] = "", missing: str = "{path}: no such {what}{hint}",
              directory: str | None = "{path}: is a directory, not a {what}", undecodable: str | None = None,
              unreadable: str = "{path}: cannot read: {kind}: {reason}") -> str:
    """The UTF-8 text of the user file ``path`` (a ``what``: "trajectory file", …), bounded by `check_readable`.

    A failure is one line of ``error``, worded by the caller so that each kind of file keeps its messages: a
    template formatted with ``path``, ``what``, ``hint`` (text, or a function giving it when needed: e.g. how
    to make the file), ``kind`` (the exception's name) and ``reason`` (the system's words). ``missing``: no
    such file; ``directory``: a directory; ``undecodable``: not UTF-8; ``unreadable``: any other failure (and
    the two before where they are None).
    """
    path = Path(path)
    check_readable(path, what, error)
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        if isinstance(e, FileNotFoundError):
            template = missing
        elif isinstance(e, IsADirectoryError) and directory is not None:
            template = directory
        elif isinstance(e, UnicodeDecodeError) and undecodable is not None:
            template = undecodable
        else:
            template = unreadable
        raise error(template.format(path=path, what=what, hint=hint() if callable(hint) else hint,
                                    kind=type(e).__name__, reason=getattr(e, "strerror", None) or e)) from None


def read_json(path: str | Path, what: str, error: type[FelisError] = FelisError, hint: str = "") -> object:
    """Parse the JSON file ``path`` (a ``what``: "push file", "drops file", …); a missing, unreadable or
    malformed file is one-line ``error`` naming it (``hint`` is added to "no such …", e.g. how to make one)."""
    path = Path(path)
    text = read_text(path, what, error, hint=hint)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise error(f"{path}: not JSON: {e.msg} at line {e.lineno} column {e.colno}") from None


def read_json_list(path: str | Path, what: str, items: str, item: str, check: Callable[[object, str], T],
                   error: type[FelisError] = FelisError) -> list[T]:
    """The entries of the JSON file ``path`` (a ``what``), a non-empty list of ``items`` ("pushes"; one-line
    ``error`` otherwise), each through ``check(entry, where)``, ``where`` naming the file and the ``item``
    with its index ("<path>: push 3")."""
    path = Path(path)
    doc = read_json(path, what, error)
    if not isinstance(doc, list) or not doc:
        raise error(f"{path}: expected a non-empty JSON list of {items}")
    return [check(entry, f"{path}: {item} {i}") for i, entry in enumerate(doc)]


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


META_KEY = "__meta__"  # the .npz member that holds a felis weights or model file's JSON metadata document


def read_meta(data: Mapping[str, object], path: str | Path, error: type[FelisError], felis_kind: str, *,
              ident: tuple[str, object, str], version: tuple[str, object, str],
              detail: Callable[[BaseException], str] = one_line, not_text: str = "is not a text string",
              not_object: str | None = "is not a JSON object") -> dict:
    """The JSON metadata document of a felis ``.npz`` (``data`` from `read_npz`): a text scalar under
    `META_KEY` holding a JSON object whose ``ident`` and ``version`` fields say what the file is.

    Every fault is one line of ``error`` naming ``path``, worded by the caller so that each kind of file
    keeps its own messages: ``felis_kind`` ends "no '__meta__' metadata; not a felis …"; ``ident`` and
    ``version`` are (field, required value, message), the message formatted with ``got`` and ``want``;
    ``detail`` words a JSON syntax error; ``not_text`` and ``not_object`` end the line
    for metadata that is not a text string or not a JSON object (``not_object=None``: a document that is not
    an object is reported as a wrong ``ident``).
    """
    if META_KEY not in data:
        raise error(f"{path}: no {META_KEY!r} metadata; not a felis {felis_kind}")
    raw = data[META_KEY]
    if raw.dtype.kind != "U" or raw.shape != ():
        raise error(f"{path}: {META_KEY!r} metadata {not_text}")
    try:
        doc = json.loads(str(raw))
    except ValueError as e:
        raise error(f"{path}: {META_KEY!r} metadata is not valid JSON ({detail(e)})") from None
    if not isinstance(doc, dict):
        if not_object is not None:
            raise error(f"{path}: {META_KEY!r} metadata {not_object}")
        doc = {}  # no fields: the ident check below names it
    for key, want, message in (ident, version):
        if doc.get(key) != want:
            raise error(f"{path}: " + message.format(got=doc.get(key), want=want))
    return doc


def check_float_arrays(arrays: Mapping[str, object], shapes: Mapping[str, tuple[int, ...]], where: str,
                       error: type[FelisError], needs: str = "the spec needs", positive: Container[str] = ()
                       ) -> None:
    """One-line ``error`` (starting with ``where``) unless ``arrays`` holds every array of ``shapes``, each
    with that shape, a float dtype and finite values, and those named in ``positive`` (standard deviations)
    all > 0; checked key by key in the order of ``shapes``. ``needs`` words the shape's origin ("the
    spec needs")."""
    import numpy as np

    for key, shape in shapes.items():
        if key not in arrays:
            raise error(f"{where} lacks array {key!r}")
        a = np.asarray(arrays[key])
        if a.shape != shape:
            raise error(f"{where} array {key!r} has shape {a.shape}, {needs} {shape}")
        if a.dtype.kind != "f":
            raise error(f"{where} array {key!r} has dtype {a.dtype}, not a float type")
        if not np.all(np.isfinite(a)):
            raise error(f"{where} array {key!r} holds non-finite values")
        if key in positive and not np.all(a > 0):
            raise error(f"{where} array {key!r} holds a non-positive standard deviation")


def check_fields(item: object, fields: tuple[str, ...], where: str, error: type[FelisError] = FelisError,
                 unknown: str = "{where}: unknown field {field!r} (fields: {fields})") -> dict:
    """``item`` as a JSON object with exactly ``fields``: one-line ``error`` naming ``where`` otherwise
    (``unknown``: the message for a field not in ``fields``, formatted with ``where``, ``field``, ``fields``)."""
    if not isinstance(item, dict):
        raise error(f"{where}: expected an object with {', '.join(fields)}, got {type(item).__name__}")
    missing = [k for k in fields if k not in item]
    if missing:
        raise error(f"{where}: missing {', '.join(missing)}")
    extra = sorted(set(item) - set(fields))
    if extra:
        raise error(unknown.format(where=where, field=extra[0], fields=", ".join(fields)))
    return item


def dataclass_from_json(cls: type[T], doc: Mapping[str, object], what: str, error: type[FelisError] = FelisError) -> T:
    """``cls(**doc)`` for the dataclass ``cls`` (the inverse of its JSON form): one-line ``error`` "``what``
    has unknown keys …" or "``what`` is incomplete: …" (a missing key; the constructor's own checks raise
    as they do)."""
    unknown = set(doc) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise error(f"{what} has unknown keys {', '.join(sorted(unknown))}")
    try:
        return cls(**doc)
    except TypeError as e:
        raise error(f"{what} is incomplete: {e}") from None


def finite_number(item: dict, key: str, where: str, error: type[FelisError] = FelisError) -> float:
    """``item[key]`` as a finite float (not a bool, not a string); one-line ``error`` otherwise."""
    import math

    v = item[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise error(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)
