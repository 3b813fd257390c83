"""Run logs: one control run written to an MCAP file as JSON messages, and read back.

Why MCAP + JSON: Foxglove opens the file as is (every topic carries a JSON Schema, encoding
``jsonschema``, so its panels show named fields), and any MCAP tool can inspect it.

Topics (log time = run time ``t`` in ns, ``int(t * 1e9)``):

=============  ===========================================================================
``/meta``      once at t=0: robot, joints, groups, rate_hz, felis_version, started_utc, extras
``/state``     every tick: t, q, dq, effort|null, height|null, imu {quat, gyro, accel}|null,
               contacts|null, faults {hardware, comm_errors, stale|null}|null
``/command``   what was sent: t, q, dq_max|null, torque|null
``/events``    t, kind, detail (safety clamp, watchdog, ...)
``/summary``   once at the end, if the caller gives one (timing, outcome)
=============  ===========================================================================

The writer, `JsonMcapWriter`, is the one MCAP writer of felis: `RunLog` adds the topics above, the servo
monitor's export (`felis.logs.monitorlog`) its ``/monitor``.

Crash safety: the writer runs MCAP unchunked (each message is a complete record on its own) and
flushes the file after every message, so a process killed mid-run leaves everything up to its last
call in the operating system's hands; only ``close()`` adds the summary section and footer.
(No ``fsync``: that would cost milliseconds per tick; a power cut may lose the page cache.)
:func:`read_log` walks the records sequentially, stops cleanly at a cut-off record and reports
``complete=False`` for such a file.

JSON cannot hold NaN or infinity: such numbers are written as ``null`` and read back as NaN.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import struct
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from felis.errors import LogError
from felis.files import MAX_LOG_BYTES, check_readable, prepare_parent
from felis.hal import Command, State
from felis.spec import RobotSpec

MAGIC = b"\x89MCAP0\r\n"
PROFILE = "felis"

# ---------------------------------------------------------------------------------------------
# JSON schemas (Foxglove reads field names and types from these)

_NUM = {"type": ["number", "null"]}
_NUMS = {"type": "array", "items": _NUM}
_NUMS_OR_NULL = {"type": ["array", "null"], "items": _NUM}
_BOOLS_OR_NULL = {"type": ["array", "null"], "items": {"type": "boolean"}}

SCHEMAS: dict[str, tuple[str, dict]] = {
    "/meta": ("felis.Meta", {
        "type": "object",
        "properties": {
            "robot": {"type": "string"},
            "joints": {"type": "array", "items": {"type": "string"}},
            "groups": {"type": "object",
                       "additionalProperties": {"type": "array", "items": {"type": "string"}}},
            "rate_hz": {"type": "number"},
            "felis_version": {"type": "string"},
            "started_utc": {"type": "string"},
        },
    }),
    "/state": ("felis.State", {
        "type": "object",
        "properties": {
            "t": _NUM,
            "q": _NUMS,
            "dq": _NUMS,
            "effort": _NUMS_OR_NULL,
            "height": _NUM,
            "imu": {"type": ["object", "null"], "properties": {
                "quat": {**_NUMS, "description": "orientation (w, x, y, z) in the world"},
                "gyro": {**_NUMS, "description": "rad/s, IMU frame"},
                "accel": {**_NUMS, "description": "m/s², IMU frame"},
            }},
            "contacts": _BOOLS_OR_NULL,
            "faults": {"type": ["object", "null"], "properties": {
                "hardware": {"type": "array", "items": {"type": "integer"}},
                "comm_errors": {"type": "integer"},
                "stale": _BOOLS_OR_NULL,
            }},
        },
    }),
    "/command": ("felis.Command", {
        "type": "object",
        "properties": {"t": _NUM, "q": _NUMS, "dq_max": _NUMS_OR_NULL, "torque": _BOOLS_OR_NULL},
    }),
    "/events": ("felis.Event", {
        "type": "object",
        "properties": {"t": _NUM, "kind": {"type": "string"}, "detail": {"type": "object"}},
    }),
    "/summary": ("felis.Summary", {"type": "object"}),
}
TOPICS = tuple(SCHEMAS)


# ---------------------------------------------------------------------------------------------
# JSON helpers


def _default(obj: Any) -> Any:
    """JSON fallback for numpy values, dataclasses, paths and anything else (as text)."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}  # encoder recurses
    return str(obj)


def _finite(obj: Any) -> Any:
    """Copy of ``obj`` (already made of plain Python values) with NaN/inf floats as None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _finite(_default(obj))
    return obj


def _floats(a: Any) -> list:
    return np.asarray(a, dtype=float).tolist()


def _bools(a: Any) -> list | None:
    return None if a is None else np.asarray(a, dtype=bool).tolist()


def _ns(t: float) -> int:
    """Log time in ns; non-finite or negative times map to 0 (MCAP times are unsigned)."""
    return int(t * 1e9) if math.isfinite(t) and t > 0 else 0


# ---------------------------------------------------------------------------------------------
# writing


class JsonMcapWriter:
    """An MCAP file of JSON messages on fixed topics, each with its JSON Schema: the one MCAP writer of felis
    (run logs, `RunLog`; the servo monitor's export, `felis.logs.monitorlog`).

    Written unchunked and flushed after every message (one whole record each), so a killed process loses
    nothing written before it died; ``close()`` adds the summary section and footer. ``topics`` maps each
    topic to (schema name, JSON Schema); ``meta`` is the ``/meta`` message written first at t=0 (when
    ``/meta`` is one of the topics). Errors are ``error(f"cannot write {what} {path}: …")``.
    """

    def __init__(self, path: str | Path, topics: dict[str, tuple[str, dict]], meta: dict | None = None, *,
                 what: str = "run log", error: type[Exception] = LogError):
        import felis  # late: felis/__init__ may one day import this module

        self.path = Path(path)
        self._what, self._error = what, error
        self._closed = False
        self._last_ns = 0
        self._encoder = json.JSONEncoder(allow_nan=False, separators=(",", ":"), default=_default)
        prepare_parent(self.path, what, error)
        try:
            self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as e:
            raise error(f"cannot write {what} {self.path}: {e.strerror or e}") from None
        try:
            self._writer = Writer(self._file, use_chunking=False, use_summary_offsets=True)
            self._writer.start(profile=PROFILE, library=f"felis-{felis.__version__}")
            self._channels = {}
            for topic, (name, schema) in topics.items():
                sid = self._writer.register_schema(name=name, encoding="jsonschema",
                                                   data=json.dumps(schema).encode())
                self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                      schema_id=sid)
            if meta is not None:
                self._put("/meta", 0, meta)
        except (OSError, error) as e:
            self._file.close()
            self._closed = True
            if isinstance(e, error):
                raise
            raise error(f"cannot write {what} {self.path}: {e.strerror or e}") from None

    def message(self, topic: str, t: float, msg: dict) -> None:
        """Write ``msg`` on ``topic`` at run time ``t`` (s; log time ``int(t * 1e9)`` ns)."""
        self._put(topic, _ns(t), msg)

    def close(self, summary: dict | None = None) -> None:
        """Write ``/summary`` (if given) and finish the file (summary section, footer). Idempotent."""
        if self._closed:
            return
        try:
            if summary is not None:
                self._put("/summary", self._last_ns, summary)
            self._writer.finish()
            self._file.flush()
        except OSError as e:
            raise self._error(f"cannot finish {self._what} {self.path}: {e.strerror or e}") from None
        finally:
            self._closed = True
            self._file.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _put(self, topic: str, log_ns: int, msg: dict) -> None:
        if self._closed:
            raise self._error(f"{self._what} {self.path} is closed; cannot log {topic}")
        try:
            text = self._encoder.encode(msg)
        except (ValueError, TypeError):  # NaN/inf (JSON has none: write null) or non-str keys
            text = self._encoder.encode(_finite(msg))
        self._last_ns = max(self._last_ns, log_ns)
        try:
            self._writer.add_message(self._channels[topic], log_time=log_ns, data=text.encode(),
                                     publish_time=log_ns)
            self._file.flush()
        except OSError as e:
            raise self._error(f"cannot write {self._what} {self.path}: {e.strerror or e}") from None


class RunLog(JsonMcapWriter):
    """Writes one run to an MCAP file, JSON messages, incrementally (unchunked records, flushed each tick).

    Every call writes one whole MCAP record and flushes the file, so a killed process loses nothing
    that was logged before it died. Cost: about 40 µs for a full 12-joint state, mostly float→text.

    >>> with RunLog("runs/drop.mcap", spec) as log:      # doctest: +SKIP
    ...     log.state(state); log.command(state.t, sent); log.event(t, "clamp", joints=["tail_yaw"])
    ...     log.close({"overruns": 0})
    """

    def __init__(self, path: str | Path, spec: RobotSpec, meta: dict | None = None):
        import felis  # late: felis/__init__ may one day import this module

        self.spec = spec
        header = {
            "robot": spec.name,
            "joints": list(spec.names),
            "groups": {g: list(js) for g, js in spec.groups.items()},
            "rate_hz": float(spec.rate_hz),
            "felis_version": felis.__version__,
            "started_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
            **(meta or {}),
        }
        super().__init__(path, SCHEMAS, header)

    # -- per tick -------------------------------------------------------------------------------

    def state(self, state: State) -> None:
        """Log one `State` on ``/state``."""
        imu = state.imu
        faults = state.faults
        msg = {
            "t": float(state.t),
            "q": _floats(state.q),
            "dq": _floats(state.dq),
            "effort": None if state.effort is None else _floats(state.effort),
            "height": None if state.height is None else float(state.height),
            "imu": None if imu is None else {
                "quat": _floats(imu.quat), "gyro": _floats(imu.gyro), "accel": _floats(imu.accel)},
            "contacts": _bools(state.contacts),
            "faults": None if faults is None else {
                "hardware": np.asarray(faults.hardware, dtype=np.int64).tolist(),
                "comm_errors": int(faults.comm_errors),
                "stale": _bools(faults.stale),
            },
        }
        self._put("/state", _ns(state.t), msg)

    def command(self, t: float, command: Command) -> None:
        """Log the command actually sent at time ``t`` on ``/command``."""
        msg = {
            "t": float(t),
            "q": _floats(command.q),
            "dq_max": None if command.dq_max is None else _floats(command.dq_max),
            "torque": _bools(command.torque),
        }
        self._put("/command", _ns(t), msg)

    def event(self, t: float, kind: str, **detail) -> None:
        """Log a discrete event (safety clamp, watchdog trip, mode change, ...) on ``/events``."""
        self._put("/events", _ns(t), {"t": float(t), "kind": str(kind), "detail": detail})

    def __enter__(self) -> RunLog:
        return self


# ---------------------------------------------------------------------------------------------
# reading


@dataclass
class LogData:
    """A run log read back; arrays in the joint order of ``joints``, NaN where a value was null."""

    path: Path
    meta: dict
    joints: list[str]
    t: np.ndarray  # (N,) state times
    q: np.ndarray  # (N, n)
    dq: np.ndarray  # (N, n)
    effort: np.ndarray | None  # (N, n); None when no state carried effort
    height: np.ndarray | None  # (N,) NaN where null; None when no state carried a height
    quat: np.ndarray | None  # (N, 4) IMU quaternions (w, x, y, z); None without an IMU
    cmd_t: np.ndarray  # (M,) command times
    cmd_q: np.ndarray  # (M, n) commands sent
    events: list[dict]  # {"t", "kind", "detail"} in file order
    summary: dict | None
    complete: bool  # False when the file was cut off (crash: no summary section / footer)
    counts: dict[str, int]  # messages per topic

    @property
    def robot(self) -> str:
        return str(self.meta.get("robot", "?"))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0


def _complete_prefix(buf: bytes, size: int) -> tuple[int, bool]:
    """Length of the run of whole records after the magic, and whether the file ends properly.

    An MCAP record is ``opcode (1 byte) | length (uint64 LE) | body``. A crash can cut the last
    record short; everything before it is intact because records are written whole and in order.
    """
    pos = len(MAGIC)
    while pos + 9 <= size:
        opcode = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        end = pos + 9 + length
        if end > size:
            break
        pos = end
        if opcode == 0x02:  # Footer: a finished file ends with the magic again
            if buf[pos:pos + len(MAGIC)] == MAGIC:
                return pos + len(MAGIC), True
            return pos, False
    return pos, False


def _read_bytes(path: Path) -> bytes:
    try:
        if not path.is_file():
            raise LogError(f"{path}: no such run log" if not path.exists() else f"{path}: not a file")
        check_readable(path, "run log", LogError, MAX_LOG_BYTES)
        data = path.read_bytes()
    except OSError as e:
        raise LogError(f"{path}: cannot read run log: {e.strerror or e}") from None
    if not data:
        raise LogError(f"{path}: empty file, not an MCAP run log")
    if not data.startswith(MAGIC):
        raise LogError(f"{path}: not an MCAP file")
    return data


def _records(path: Path) -> tuple[list, bool]:
    """The MCAP records of the file's intact prefix, and whether the file ended properly."""
    data = _read_bytes(path)
    end, complete = _complete_prefix(data, len(data))
    stream = io.BytesIO(data if end == len(data) else data[:end])
    stream.seek(len(MAGIC))  # checked in _read_bytes
    # skip_magic: no trailing magic expected either (a cut-off file has none; _complete_prefix
    # already checked it on a finished one and left it inside `end`, where the reader reads it)
    out = []
    try:
        for rec in StreamReader(stream, skip_magic=True, validate_crcs=False).records:
            out.append(rec)
    except EndOfFile:
        pass  # the normal end of the intact prefix of a cut-off file
    except (McapError, struct.error, UnicodeDecodeError, ValueError):
        complete = False  # garbage inside whole records: keep what was read before it
    return out, complete


def _rows(rows: list, n: int, what: str, path: Path) -> np.ndarray:
    """(N, n) float array from lists with None (→ NaN); a row of the wrong length is an error."""
    for i, r in enumerate(rows):
        if len(r) != n:
            raise LogError(f"{path}: {what} message {i} has {len(r)} values, the log has {n} joints")
    return np.array(rows, dtype=float).reshape(len(rows), n)


def read_log(path: str | Path) -> LogData:
    """Read a felis run log, complete or cut off by a crash.

    Raises LogError for a missing file, a file that is not MCAP, or an MCAP file without a felis
    ``/meta`` message (not a felis log, or cut off before its first message).
    """
    path = Path(path)
    records, complete = _records(path)
    topics: dict[int, str] = {}
    counts: Counter[str] = Counter({t: 0 for t in TOPICS})
    meta: dict | None = None
    summary: dict | None = None
    states: list[dict] = []
    commands: list[dict] = []
    events: list[dict] = []
    for rec in records:
        if isinstance(rec, Channel):
            topics[rec.id] = rec.topic
            continue
        if not isinstance(rec, Message):
            continue
        topic = topics.get(rec.channel_id)
        if topic is None:
            continue
        counts[topic] += 1
        if topic not in TOPICS:
            continue
        try:
            msg = json.loads(rec.data)
        except (ValueError, UnicodeDecodeError):
            raise LogError(f"{path}: {topic} message {counts[topic]} is not valid JSON") from None
        if not isinstance(msg, dict):
            raise LogError(f"{path}: {topic} message {counts[topic]} is not a JSON object")
        if topic == "/state":
            states.append(msg)
        elif topic == "/command":
            commands.append(msg)
        elif topic == "/events":
            events.append(msg)
        elif topic == "/meta" and meta is None:
            meta = msg
        elif topic == "/summary":
            summary = msg
    if meta is None or not isinstance(meta.get("joints"), list):
        raise LogError(f"{path}: not a felis run log (no /meta message with joints)")
    joints = [str(j) for j in meta["joints"]]
    n = len(joints)
    try:
        t = np.array([s.get("t") for s in states], dtype=float)
        q = _rows([s["q"] for s in states], n, "/state", path)
        dq = _rows([s["dq"] for s in states], n, "/state", path)
        effort = height = quat = None
        if any(s.get("effort") is not None for s in states):
            effort = _rows([s.get("effort") or [None] * n for s in states], n, "/state effort", path)
        if any(s.get("height") is not None for s in states):
            height = np.array([s.get("height") for s in states], dtype=float)
        if any(s.get("imu") is not None for s in states):
            quats = [(s.get("imu") or {}).get("quat") or [None] * 4 for s in states]
            quat = _rows(quats, 4, "/state imu", path)
        cmd_t = np.array([c.get("t") for c in commands], dtype=float)
        cmd_q = _rows([c["q"] for c in commands], n, "/command", path)
    except (KeyError, TypeError) as e:
        raise LogError(f"{path}: malformed felis run log ({e!r} in a message)") from None
    return LogData(path=path, meta=meta, joints=joints, t=t, q=q, dq=dq, effort=effort, height=height,
                   quat=quat, cmd_t=cmd_t, cmd_q=cmd_q, events=events, summary=summary,
                   complete=complete, counts=dict(counts))


def log_info(path: str | Path) -> dict:
    """A JSON-able overview of a run log (for ``felis log info`` and scripts)."""
    data = read_log(path)
    n = len(data.t)
    duration = data.duration
    return {
        "path": str(data.path),
        "robot": data.robot,
        "joints": data.joints,
        "complete": data.complete,
        "duration_s": round(duration, 6),
        "counts": data.counts,
        "rate": round((n - 1) / duration, 3) if n > 1 and duration > 0 else 0.0,
        "events": dict(Counter(str(e.get("kind")) for e in data.events)),
        "summary": data.summary,
        "size_bytes": data.path.stat().st_size,
    }
