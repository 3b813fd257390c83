"""Run logs read back (`read_log` → `LogData`, `channel_messages`, `log_info`): the records of a file's intact
prefix (a file cut by a crash reads as ``complete=False``), Foxglove's Protobuf schemas decoded from the schemas the
file carries, felis ≤ 0.2's JSON form refused with what to do. The channels: `felis.logs.runlog`."""

from __future__ import annotations

import dataclasses
import io
import json
import struct
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from felis.errors import LogError
from felis.files import MAX_LOG_BYTES, check_readable
from felis.logs.mcap import MAGIC
from felis.logs.messages import as_dict

STATE_TOPICS = ("/joint_states", "/joint_commands", "/tf", "/imu", "/contacts", "/base", "/faults", "/timing")
TOPICS = ("/meta", "/robot", *STATE_TOPICS, "/log", "/summary")
OLD_TOPICS = ("/state", "/command", "/events")  # felis ≤ 0.2: JSON only

# ---------------------------------------------------------------------------------------------
# reading


@dataclass
class LogData:
    """A run log read back; arrays in the joint order of ``joints``, NaN where a value was missing. Times are run
    times (s since the log's start, the ``/meta`` message)."""

    path: Path
    meta: dict
    joints: list[str]
    t: np.ndarray  # (N,) state times
    q: np.ndarray  # (N, n)
    dq: np.ndarray  # (N, n)
    effort: np.ndarray | None  # (N, n); None when no state carried effort
    height: np.ndarray | None  # (N,) NaN where missing; None when no state carried a height
    quat: np.ndarray | None  # (N, 4) IMU quaternions (w, x, y, z); None without an IMU
    cmd_t: np.ndarray  # (M,) command times
    cmd_q: np.ndarray  # (M, n) commands sent
    events: list[dict]  # {"t", "kind", "detail"} in file order
    summary: dict | None
    complete: bool  # False when the file was cut off (crash: no summary section / footer)
    counts: dict[str, int]  # messages per topic
    contacts: np.ndarray | None = None  # (N, feet) bool; None without foot contacts
    feet: list[str] = dataclasses.field(default_factory=list)
    start_ns: int = 0  # log time of run time 0 (epoch ns)

    @property
    def robot(self) -> str:
        return str(self.meta.get("robot", "?"))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0


def _complete_prefix(buf: bytes, size: int) -> tuple[int, bool]:
    """Length of the run of whole records after the magic, and whether the file ends properly.

    An MCAP record is ``opcode (1 byte) | length (uint64 LE) | body``. A crash can cut the last
    record short; everything before it is intact because records are written in order. The one record
    written out of order is the chunk being filled: the SDK's writer puts placeholders in its header, streams
    the data after it, then goes back and overwrites the header field by field (`_whole_chunk`), so a kill can
    leave a chunk whose bytes are all there but whose header is half written; it ends the prefix too.
    """
    pos = len(MAGIC)
    while pos + 9 <= size:
        opcode = buf[pos]
        (length,) = struct.unpack_from("<Q", buf, pos + 1)
        end = pos + 9 + length
        if end > size or (opcode == 0x06 and not _whole_chunk(buf, pos + 9, length)):
            break
        pos = end
        if opcode == 0x02:  # Footer: a finished file ends with the magic again
            if buf[pos:pos + len(MAGIC)] == MAGIC:
                return pos + len(MAGIC), True
            return pos, False
    return pos, False


_CHUNK_FIXED = struct.Struct("<QQQII")  # message start and end time, uncompressed size and CRC, compression length
_UNSET = 2**64 - 1  # the writer's placeholder for a size it has not yet written


def _whole_chunk(buf: bytes, body: int, length: int) -> bool:
    """Whether the Chunk record whose body starts at ``body`` has a finished header.

    The body is ``start (u64) | end (u64) | uncompressed size (u64) | CRC (u32) | compression (u32 length +
    bytes) | compressed size (u64) | data``. The writer's placeholders are ``2**64 - 1`` for the record length
    and all three sizes; it overwrites them in file order, the compressed size last, so the header is finished
    exactly when the compressed size accounts for the rest of the record (and the uncompressed size is set).
    """
    if length < _CHUNK_FIXED.size + 8:
        return False
    *_, uncompressed, _crc, name_len = _CHUNK_FIXED.unpack_from(buf, body)
    head = _CHUNK_FIXED.size + name_len + 8
    if uncompressed == _UNSET or head > length:
        return False
    (compressed,) = struct.unpack_from("<Q", buf, body + head - 8)
    return head + compressed == length


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
    """The MCAP records of the file's intact prefix (chunks opened), and whether the file ended properly."""
    data = _read_bytes(path)
    end, complete = _complete_prefix(data, len(data))
    stream = io.BytesIO(data if end == len(data) else data[:end])
    stream.seek(len(MAGIC))
    out = []
    try:
        for rec in StreamReader(stream, skip_magic=True, validate_crcs=False).records:
            out.append(rec)
    except EndOfFile:
        pass  # the normal end of the intact prefix of a cut-off file
    except (McapError, struct.error, UnicodeDecodeError, ValueError, RuntimeError, OverflowError):
        complete = False  # garbage inside whole records: keep what was read before it
    return out, complete


def _messages(records: list) -> tuple[dict[int, Schema], dict[int, Channel], dict[str, list]]:
    """Schemas and channels by id, and every message by topic as (log time, data, channel), in file order."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    raw: dict[str, list] = {}
    for rec in records:
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is not None:
                raw.setdefault(ch.topic, []).append((rec.log_time, rec.data, ch))
    return schemas, channels, raw


_CLASSES: dict[tuple[str, bytes], type] = {}


def protobuf_class(name: str, data: bytes) -> type:
    """The protobuf message class of schema ``name`` from its FileDescriptorSet (cached)."""
    key = (name, data)
    cls = _CLASSES.get(key)
    if cls is None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        pool = descriptor_pool.DescriptorPool()
        for f in descriptor_pb2.FileDescriptorSet.FromString(data).file:
            pool.Add(f)
        cls = _CLASSES[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    return cls


def _joint_rows(msgs: list, joints: list[str], path: Path, topic: str):
    """(N, n) position, velocity, effort from JointStates messages (joints matched by name; NaN if absent)."""
    n, index = len(joints), {j: i for i, j in enumerate(joints)}
    out = np.full((3, len(msgs), n), np.nan)
    has_effort = False
    for k, m in enumerate(msgs):
        for js in m.joints:
            i = index.get(js.name)
            if i is None:
                raise LogError(f"{path}: {topic} message {k} names joint {js.name!r}, not one of the log's joints")
            if js.HasField("position"):
                out[0, k, i] = js.position
            if js.HasField("velocity"):
                out[1, k, i] = js.velocity
            if js.HasField("effort"):
                out[2, k, i] = js.effort
                has_effort = True
    return out[0], out[1], (out[2] if has_effort else None)


def read_log(path: str | Path) -> LogData:
    """Read a felis run log, complete or cut off by a crash.

    Raises LogError for a missing file, a file that is not MCAP, an MCAP file without a felis ``/meta`` message
    (not a felis log, or cut off before its first chunk), and a log of felis 0.2's form (saying what to do).
    """
    path = Path(path)
    records, complete = _records(path)
    schemas, channels, raw = _messages(records)
    counts: Counter[str] = Counter({t: 0 for t in ("/meta", "/joint_states", "/joint_commands", "/log")})
    counts.update({topic: len(items) for topic, items in raw.items()})
    topics = {c.topic for c in channels.values()}
    if "/state" in topics and "/joint_states" not in topics:
        raise LogError(f"{path}: a felis 0.2 log (JSON /state and /command topics); this felis reads the Foxglove "
                       "form of felis ≥ 0.3. Read it with felis 0.2 (pip install 'felis==0.2.*'), or record the run "
                       "again")

    def decode(topic: str) -> list[tuple[int, Any]]:
        out = []
        for i, (ns, data, ch) in enumerate(raw.get(topic, [])):
            sch = schemas.get(ch.schema_id)
            try:
                if ch.message_encoding == "json":
                    msg = json.loads(data)
                    if not isinstance(msg, dict):
                        raise ValueError("not an object")
                elif ch.message_encoding == "protobuf" and sch is not None:
                    msg = protobuf_class(sch.name, sch.data).FromString(data)
                    if sch.name.startswith("felis."):  # felis's own messages read as their JSON form did
                        msg = as_dict(msg)
                else:
                    raise ValueError(f"unknown encoding {ch.message_encoding!r}")
            except Exception:  # noqa: BLE001 - any decoding failure is the same fault for the user
                raise LogError(f"{path}: {topic} message {i + 1} cannot be decoded ({ch.message_encoding})") from None
            out.append((ns, msg))
        return out

    metas = decode("/meta")
    if not metas or not isinstance(metas[0][1].get("joints"), list):
        raise LogError(f"{path}: not a felis run log (no /meta message with joints)")
    start_ns, meta = metas[0]
    joints = [str(j) for j in meta["joints"]]
    n = len(joints)

    def times(items) -> np.ndarray:
        return np.array([(ns - start_ns) / 1e9 for ns, _ in items], dtype=float)

    states = decode("/joint_states")
    t = times(states)
    q, dq, effort = _joint_rows([m for _, m in states], joints, path, "/joint_states")
    commands = decode("/joint_commands")
    cmd_t = times(commands)
    cmd_q, _, _ = _joint_rows([m for _, m in commands], joints, path, "/joint_commands")
    state_ns = np.array([ns for ns, _ in states], dtype=np.int64)

    def aligned(topic: str, width: int, values):
        """(N, width) values of ``topic`` at the states' log times (NaN where missing); None without any."""
        items = decode(topic)
        if not items:
            return None
        out = np.full((len(states), width), np.nan)
        ns = np.array([x for x, _ in items], dtype=np.int64)
        at = np.searchsorted(state_ns, ns)
        for k, (i, (_, m)) in enumerate(zip(at, items, strict=True)):
            if i < len(states) and state_ns[i] == ns[k]:
                out[i] = values(m)
        return out

    def _quat(m):
        o = m.get("orientation") or {}
        return [o.get("w", np.nan), o.get("x", np.nan), o.get("y", np.nan), o.get("z", np.nan)]

    quat = aligned("/imu", 4, _quat)
    h = aligned("/base", 1, lambda m: [m.get("height", np.nan)])
    height = None if h is None else h[:, 0]
    feet = [str(f) for f in meta.get("feet", [])]
    contacts = None
    c = decode("/contacts")
    if c:
        feet = list(c[0][1].keys())
        contacts = np.zeros((len(states), len(feet)), dtype=bool)
        at = np.searchsorted(state_ns, np.array([x for x, _ in c], dtype=np.int64))
        for i, (ns, m) in zip(at, c, strict=True):
            if i < len(states) and state_ns[i] == ns:
                contacts[i] = [bool(m.get(f, False)) for f in feet]
    events = []
    for ns, m in decode("/log"):
        kind, _, rest = m.message.partition(" ")
        try:
            detail = json.loads(rest) if rest else {}
        except ValueError:
            detail = {"message": rest}
        events.append({"t": (ns - start_ns) / 1e9, "kind": m.name or kind, "detail": detail})
    summaries = decode("/summary")
    summary = summaries[-1][1] if summaries else None
    return LogData(path=path, meta=meta, joints=joints, t=t, q=q.reshape(-1, n), dq=dq.reshape(-1, n),
                   effort=effort, height=height, quat=quat, cmd_t=cmd_t, cmd_q=cmd_q.reshape(-1, n), events=events,
                   summary=summary, complete=complete, counts=dict(counts), contacts=contacts, feet=feet,
                   start_ns=int(start_ns))


def channel_messages(path: str | Path, topics: set[str] | None = None) -> dict[str, list[tuple[float, dict]]]:
    """Every message of the log's JSON channels and felis's own Protobuf ones (``felis.*``), by topic, as (run time
    s, dict), in file order: what `felis.logs.export` writes for channels `read_log` does not gather (``/balance``,
    ``/phase``, …). ``topics`` limits it. Foxglove's Protobuf channels are left to `read_log`."""
    path = Path(path)
    records, _ = _records(path)
    schemas, _, raw = _messages(records)
    if not raw.get("/meta"):
        raise LogError(f"{path}: not a felis run log (no /meta message)")
    start = raw["/meta"][0][0]
    out: dict[str, list[tuple[int, dict]]] = {}
    for topic, items in raw.items():
        if topics is not None and topic not in topics:
            continue
        for ns, data, ch in items:
            sch = schemas.get(ch.schema_id)
            try:
                if ch.message_encoding == "json":
                    msg = json.loads(data)
                elif ch.message_encoding == "protobuf" and sch is not None and sch.name.startswith("felis."):
                    msg = as_dict(protobuf_class(sch.name, sch.data).FromString(data))
                else:
                    continue  # Foxglove's Protobuf channels: `read_log`'s
            except Exception:  # noqa: BLE001 - any decoding failure is the same fault for the user
                raise LogError(f"{path}: a {topic} message cannot be decoded ({ch.message_encoding})") from None
            if isinstance(msg, dict):
                out.setdefault(topic, []).append((ns, msg))
    return {t: [((ns - start) / 1e9, m) for ns, m in items] for t, items in out.items()}


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
        "started_utc": data.meta.get("started_utc"),
        "duration_s": round(duration, 6),
        "counts": data.counts,
        "rate": round((n - 1) / duration, 3) if n > 1 and duration > 0 else 0.0,
        "events": dict(Counter(str(e.get("kind")) for e in data.events)),
        "summary": data.summary,
        "size_bytes": data.path.stat().st_size,
    }

