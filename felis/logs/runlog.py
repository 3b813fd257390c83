"""Run logs: one control run written to an MCAP file through the Foxglove SDK, with Foxglove's well-known schemas,
and read back.

Why this form: Foxglove, Lichtblick and Rerun open it as is and draw the robot in 3D; any MCAP tool reads it.

Channels (log time: epoch ns, ``start + t``, where start is the wall clock when the log opened and t the run time
of the message; one time base for run, monitor and eval logs):

==================  ========================  ===================================================================
``/meta``           JSON (felis.Meta)         once, first: robot, joints, groups, rate_hz, felis_version,
                                              started_utc, command, and what the caller adds (backend, drop…)
``/robot``          foxglove.SceneUpdate      once: the robot's geoms on its body frames, the floor, a target path
``/joint_states``   foxglove.JointStates      every tick: per joint name, position (rad or m), velocity, effort
``/joint_commands`` foxglove.JointStates      every tick: the positions actually sent
``/tf``             foxglove.FrameTransforms  every tick: every body's pose in ``world`` (when the caller gives poses)
``/imu``            felis.Imu (Protobuf)      orientation {x, y, z, w}, angular_velocity, linear_acceleration
                                              {x, y, z}, tilt_deg
``/contacts``       felis.Contacts (Protob.)  one boolean per foot, by name
``/base``           felis.Base (Protobuf)     height (m), when the backend knows it
``/faults``         JSON (felis.Faults)       hardware (error bits per joint), comm_errors, stale; when it changes
``/timing``         felis.Timing (Protobuf)   control_ms: read → write time of the tick
``/log``            foxglove.Log              events: name = the kind (clamp, watchdog, comm_lost, …), message =
                                              kind and its details as JSON
``/summary``        JSON (felis.Summary)      once at the end, if the caller gives one (timing, outcome)
==================  ========================  ===================================================================

The skills add their own (`felis.logs.skills`): ``/balance`` (the XCoM monitor's margin, alarm, warning, ξ, CoM)
and ``/phase`` (the gait phase its gate reads) each tick while a balance monitor runs; ``/landing`` (the verdict)
at the end of a drop.

Every JSON schema follows the rules of Foxglove's JSON-schema parser (one type per field, ``properties`` on
every object, ``items`` on every array, no arrays of arrays; `schema_of` builds them from example values).

Speed: a tick's messages are not encoded when the loop logs them: the states, commands and times are kept (and
the body poses copied) until the chunk is finished, at most `FLUSH_S` of run time later, and then encoded all
together, channel by channel: the Protobuf ones of all the kept ticks filled into templates in one numpy scatter
per channel (`felis.logs.wire`, `felis.logs.messages`). Done together they cost less than one tick at a time
between physics steps, which evict the interpreter's working set from the CPU caches; the per-tick channels are all
Protobuf because formatting four of them as JSON text was 40 % of the log's cost. A `State` and a
`Command` are therefore not to be changed after they are logged (the robots make new ones each tick). The live
view gets them in the same batches: a viewer sees a run at most `FLUSH_S` late. Events (``/log``) and messages
are written at once.

Crash safety: the file is chunked (lz4) and indexed, and each chunk is finished and handed to the operating
system at the start of the first tick by which both `FLUSH_S` of run time and `FLUSH_WALL_S` (half of it) of wall
time have passed since the last, so a process killed mid-run loses at most the last `FLUSH_S` plus one tick (the
kept ticks belong to the chunk that is lost anyway) of a run that keeps pace with the clock (hardware,
servo-in-the-loop, a real-time simulation), and a simulation running faster than real time loses at most the ticks
of its last `FLUSH_WALL_S` of wall time, plus one. Finishing a chunk costs about half a millisecond whatever it
holds: a simulation at 8× real time finishing one every `FLUSH_S` of run time spent a tenth of its time on that.
:func:`read_log` walks the records of the intact prefix
and reports ``complete=False`` for a cut file. (No ``fsync``: a power cut may lose the page cache.)

``--live``: the same channels go to a `felis.logs.live.LiveView` (Foxglove WebSocket server), if one is given.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import struct
import sys
import time
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import foxglove
import numpy as np
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import (
    Color,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransforms,
    JointStates,
    LinePrimitive,
    Log,
    LogLevel,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from felis.errors import LogError
from felis.files import MAX_LOG_BYTES, check_readable, prepare_parent
from felis.hal import Command, State
from felis.logs.messages import BASE, IMU, TIMING, as_dict, contacts_message
from felis.logs.wire import FrameTransformsEncoder, JointStatesEncoder, runs
from felis.scene import BodyPoses, RobotScene
from felis.spec import RobotSpec

MAGIC = b"\x89MCAP0\r\n"
PROFILE = ""  # Foxglove's well-known schemas in protobuf and JSON: no ROS profile
COMPRESSION = MCAPCompression.Lz4  # per chunk; lz4 and zstd cost about the same at this chunk size
FLUSH_S = 0.08  # a chunk is finished at least this often (run time): the most a killed process loses, plus a tick
FLUSH_WALL_S = FLUSH_S / 2  # … and not more often than this (wall time): a simulation faster than real time
STATE_TOPICS = ("/joint_states", "/joint_commands", "/tf", "/imu", "/contacts", "/base", "/faults", "/timing")
TOPICS = ("/meta", "/robot", *STATE_TOPICS, "/log", "/summary")
OLD_TOPICS = ("/state", "/command", "/events")  # felis ≤ 0.2: JSON only

# ---------------------------------------------------------------------------------------------
# JSON schemas (Foxglove's rules: one type per field, properties on objects, items on arrays)

_NUM = {"type": "number"}
_XYZ = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}

FAULTS_SCHEMA = {"type": "object", "title": "felis.Faults", "properties": {
    "hardware": {"type": "array", "items": {"type": "integer"}, "description": "hardware error bits per joint"},
    "comm_errors": {"type": "integer"},
    "stale": {"type": "array", "items": {"type": "boolean"}, "description": "joints whose reading is old"}}}


def schema_of(value: Any, title: str | None = None) -> dict:
    """A JSON schema of ``value`` (already made JSON-able by `jsonable`) that Foxglove's parser accepts."""
    if isinstance(value, bool):
        out: dict = {"type": "boolean"}
    elif isinstance(value, int):
        out = {"type": "integer"}
    elif isinstance(value, float) or value is None:
        out = {"type": "number"}
    elif isinstance(value, str):
        out = {"type": "string"}
    elif isinstance(value, dict):
        out = {"type": "object", "properties": {k: schema_of(v) for k, v in value.items()}}
    elif isinstance(value, list):
        out = {"type": "array", "items": _merge([schema_of(v) for v in value if v is not None])}
    else:
        out = {"type": "string"}
    if title is not None:
        out["title"] = title
    return out


def _merge(schemas: list[dict]) -> dict:
    """One schema for a list's items: the first item's type; objects merge their properties."""
    if not schemas:
        return {"type": "number"}
    first = schemas[0]
    if first["type"] == "number" and any(s["type"] == "integer" for s in schemas):
        return first
    if first["type"] == "integer" and any(s["type"] == "number" for s in schemas):
        return {"type": "number"}
    if first["type"] != "object":
        return first
    props: dict = {}
    for s in schemas:
        if s["type"] == "object":
            for k, v in s["properties"].items():
                props.setdefault(k, v)
    return {"type": "object", "properties": props}


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    return str(obj)


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values that fit one schema: numpy → Python, NaN/inf → None, keys → str; None values
    in objects are left out (Foxglove has no null type); an array of arrays becomes an array of objects
    ``{"items": […]}`` (Foxglove's parser takes no nested arrays)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, dict):
        out = {str(k): jsonable(v) for k, v in obj.items()}
        return {k: v for k, v in out.items() if v is not None}
    if isinstance(obj, (list, tuple, set, frozenset, np.ndarray)):
        items = [jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
        if any(isinstance(v, list) for v in items):
            items = [{"items": v} if isinstance(v, list) else v for v in items]
        return items
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    return jsonable(_default(obj))


def _text(msg: Any) -> bytes:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


# ---------------------------------------------------------------------------------------------
# writing


def _remove_old(path: Path) -> None:
    """Unlink an old log at ``path`` before a new one is written there: the file system frees an unlinked file
    about fifty times faster than it truncates one on open (ext4: 0.05 ms against 2.4 ms for a 2 s cat log,
    ``bench/sim_speed.py`` writes one per episode). A symbolic link is left alone (written through, as
    before); a file that cannot be removed is left for the open to report."""
    try:
        if path.is_file() and not path.is_symlink():
            path.unlink()
    except OSError:
        pass


def _stamp(ns: int) -> Timestamp:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(sec=sec, nsec=nsec)


class McapLog:
    """The one MCAP writer of felis: channels in a Foxglove SDK context, written to ``path`` (chunked, indexed,
    flushed every `FLUSH_S` of log time) and, when ``live`` is given, served by that `LiveView` too.

    ``path`` may be None (a live view only). ``meta`` is the ``/meta`` message (JSON, its schema from its
    values) written first at log time ``start_ns``. Errors: ``error(f"cannot write {what} {path}: …")``.
    """

    def __init__(self, path: str | Path | None, meta: dict, *, what: str = "run log",
                 error: type[Exception] = LogError, live=None):
        self.path = None if path is None else Path(path)
        self._what, self._error = what, error
        self._closed = False
        self.start_ns = time.time_ns()
        self._last_ns = self.start_ns
        self._flushed_ns = self.start_ns
        self._flushed_wall = time.monotonic_ns()
        self._contexts = []
        self._writer = None
        self.live = live
        self._pending: list[tuple] = []  # deferred writes (`defer`)
        if self.path is not None:
            prepare_parent(self.path, what, error)
            _remove_old(self.path)
            ctx = foxglove.Context()
            options = MCAPWriteOptions(compression=COMPRESSION, chunk_size=None, profile=PROFILE,
                                       compression_level=1, compression_threads=0)
            try:
                self._writer = foxglove.open_mcap(self.path, allow_overwrite=True, context=ctx,
                                                  writer_options=options)
            except (OSError, RuntimeError, ValueError) as e:
                raise error(f"cannot write {what} {self.path}: {getattr(e, 'strerror', None) or e}") from None
            self._contexts.append(ctx)
        if live is not None:
            self._contexts.append(live.context)
        self._outs: dict[str, tuple] = {}
        self.meta = jsonable(meta)
        self.latched("/meta", schema_of(self.meta, "felis.Meta"), _text(self.meta), self.start_ns)
        self.flush()

    # -- channels -------------------------------------------------------------------------------

    def channel(self, topic: str, schema: dict | foxglove.Schema, encoding: str = "json"):
        """A function ``put(ns, data: bytes)`` that logs on ``topic`` to the file and the live view."""
        if isinstance(schema, dict):
            chans = [foxglove.Channel(topic, schema=schema, context=c) for c in self._contexts]
        else:
            chans = [foxglove.Channel(topic, schema=schema, message_encoding=encoding, context=c)
                     for c in self._contexts]
        logs = tuple(c.base.log for c in chans)
        if self.live is None:
            one = logs[0]

            def put(ns: int, data: bytes) -> None:
                one(data, ns)
        else:
            self.live.register(topic, chans[-1])
            watched = self.live.watchers(topic)
            live_log = logs[-1]
            file_log = logs[0] if len(logs) > 1 else None

            def put(ns: int, data: bytes) -> None:
                if file_log is not None:
                    file_log(data, ns)
                if watched[0]:
                    live_log(data, ns)
        self._outs[topic] = (chans, put)
        return put

    def latched(self, topic: str, schema, data: bytes, ns: int, encoding: str = "json") -> None:
        """Log one message that a viewer needs whenever it connects (meta, scene): written once to the file
        and sent again to each live client that subscribes."""
        put = self.channel(topic, schema, encoding)
        self._check_open()
        put(ns, data)
        self._last_ns = max(self._last_ns, ns)
        if self.live is not None:
            self.live.latch(topic, data, ns)

    # -- deferred writing -------------------------------------------------------------------------

    def defer(self, fn, *args) -> None:
        """Run ``fn(*args)`` (an encode and write) at the next chunk boundary, with the other deferred ones in
        order: at most `FLUSH_S` of run time later, the time after which the chunk would be handed to the
        operating system anyway, so a crash loses no more than before. Why: writes done together cost less than one
        at a time between physics steps (module doc, "Speed")."""
        self._pending.append((fn, args))

    def _write_pending(self) -> None:
        pending = self._pending
        if pending:
            self._pending = []
            for fn, args in pending:
                fn(*args)

    def message(self, topic: str, t: float, msg: dict, schema: dict | None = None) -> None:
        """Write the JSON ``msg`` on ``topic`` at run time ``t`` (s); the channel is made on first use with
        ``schema`` (default: from ``msg``)."""
        self._check_open()
        self._message(topic, t, jsonable(msg), schema)

    def _message(self, topic: str, t: float, msg, schema) -> None:
        out = self._outs.get(topic)
        put = out[1] if out else self.channel(topic, schema or schema_of(msg, f"felis.{topic.strip('/').title()}"))
        ns = self.ns(t)
        self._tick(ns)
        put(ns, _text(msg))

    def ns(self, t: float) -> int:
        """Log time (epoch ns) of run time ``t`` (s); non-finite or negative times map to the start."""
        return self.start_ns + (int(round(t * 1e9)) if math.isfinite(t) and t > 0 else 0)

    def _tick(self, ns: int) -> None:
        if ns > self._last_ns:
            self._last_ns = ns
        if ns - self._flushed_ns >= FLUSH_NS:
            wall = time.monotonic_ns()
            if wall - self._flushed_wall >= FLUSH_WALL_NS:  # faster than real time: by the wall clock (module doc)
                self.flush()
                self._flushed_ns, self._flushed_wall = ns, wall

    def flush(self) -> None:
        """Write what is deferred, finish the current chunk and hand it to the operating system."""
        self._write_pending()
        if self._writer is not None:
            try:
                self._writer.flush()
            except (OSError, RuntimeError) as e:
                raise self._error(f"cannot write {self._what} {self.path}: {e}") from None

    def _check_open(self) -> None:
        if self._closed:
            raise self._error(f"{self._what} {self.path} is closed; cannot log")

    def close(self, summary: dict | None = None) -> None:
        """Write ``/summary`` (if given) and finish the file (summary section, footer). Idempotent."""
        if self._closed:
            return
        try:
            self._write_pending()
            if summary is not None:
                s = jsonable(summary)
                put = self.channel("/summary", schema_of(s, "felis.Summary"))
                put(self._last_ns, _text(s))
            if self._writer is not None:
                self._writer.close()
        except (OSError, RuntimeError) as e:
            raise self._error(f"cannot finish {self._what} {self.path}: {e}") from None
        finally:
            self._closed = True
            registry = getattr(getattr(foxglove, "channel", None), "_channels_by_id", None)
            for chans, _ in self._outs.values():
                for c in chans:
                    c.close()
                    if isinstance(registry, dict):  # the SDK keeps every channel it made: let ours go
                        registry.pop(c.id(), None)
            if self.live is not None:
                self.live.unlatch()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


FLUSH_NS = int(FLUSH_S * 1e9)
FLUSH_WALL_NS = int(FLUSH_WALL_S * 1e9)
_LEVEL = {"watchdog": LogLevel.Error, "comm_lost": LogLevel.Error, "hardware_error": LogLevel.Error,
          "torque_lost": LogLevel.Error, "bus_watchdog": LogLevel.Error, "imu_lost": LogLevel.Warning,
          "read_failed": LogLevel.Warning, "interrupted": LogLevel.Warning, "clamp": LogLevel.Info,
          "nonfinite": LogLevel.Warning}


class RunLog(McapLog):
    """Writes one run: joint states and commands, body transforms, IMU, contacts, events (module doc).

    ``scene`` (`felis.scene.RobotScene`) is written once on ``/robot``; ``poses`` (`felis.scene.BodyPoses`) gives
    ``/tf`` each tick; ``live`` (`felis.logs.live.LiveView`) serves the same channels; ``path`` None: live only.

    >>> with RunLog("runs/drop.mcap", spec) as log:      # doctest: +SKIP
    ...     log.state(state); log.command(state.t, sent); log.event(t, "clamp", joints=["tail_yaw"])
    ...     log.close({"overruns": 0})
    """

    def __init__(self, path: str | Path | None, spec: RobotSpec, meta: dict | None = None, *,
                 scene: RobotScene | None = None, poses: BodyPoses | None = None, live=None):
        import felis  # late: felis/__init__ may one day import this module

        self.spec = spec
        self._ticks: list[tuple] = []  # deferred (ns, state, poses), (ns, q sent), (ns, control s)
        self._cmds: list[tuple] = []
        self._times: list[tuple] = []
        header = {
            "robot": spec.name,
            "joints": list(spec.names),
            "groups": {g: list(js) for g, js in spec.groups.items()},
            "rate_hz": float(spec.rate_hz),
            "felis_version": felis.__version__,
            "started_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
            "command": " ".join(["felis", *sys.argv[1:]]) if Path(sys.argv[0]).name == "felis" else " ".join(sys.argv),
            **(meta or {}),
        }
        super().__init__(path, header, live=live)
        names = list(spec.names)
        self._js_full = JointStatesEncoder(names, ("position", "velocity", "effort"))
        self._js_noeff = JointStatesEncoder(names, ("position", "velocity"))
        self._jc = JointStatesEncoder(names, ("position",))
        js_schema = JointStates.get_schema()
        self._put_js = self.channel("/joint_states", js_schema, "protobuf")
        self._put_jc = self.channel("/joint_commands", js_schema, "protobuf")
        self._put_imu = self._put_contacts = self._put_base = self._put_faults = self._put_timing = None
        self._put_log = self.channel("/log", Log.get_schema(), "protobuf")
        feet = [str(f) for f in spec.sensors.contacts]
        self._feet = feet
        self._contacts_msg = contacts_message(feet)
        self._last_faults: tuple | None = None
        self._faults_seen = None
        self._poses = poses
        self._tf = self._put_tf = None
        if poses is not None:
            self._tf = FrameTransformsEncoder(poses.bodies)
            self._put_tf = self.channel("/tf", FrameTransforms.get_schema(), "protobuf")
        if scene is not None:
            self.latched("/robot", SceneUpdate.get_schema(), scene_update(scene, self.start_ns).encode(),
                         self.start_ns, "protobuf")
        self.flush()

    # -- per tick -------------------------------------------------------------------------------

    def state(self, state: State) -> None:
        """Log one `State`: ``/joint_states``, ``/tf``, and ``/imu``, ``/contacts``, ``/base``, ``/faults``
        where the state has them. The body poses are taken now (they may read a simulation that moves on); the
        messages are encoded at the next chunk boundary (`McapLog.defer`): a `State` is not changed after it
        is read."""
        self._check_open()
        ns = self.ns(state.t)
        self._tick(ns)
        v = None
        if self._poses is not None:
            v = self._poses(state)
            if v is not None:
                v = v.copy()
        self._ticks.append((ns, state, v))

    def _write_pending(self) -> None:
        """The deferred ticks, channel by channel: the Protobuf ones of all the ticks in one scatter each
        (`felis.logs.wire`), then the JSON ones tick by tick, then the other deferred writes."""
        ticks, cmds, times = self._ticks, self._cmds, self._times
        if ticks:
            self._ticks = []
            ns = [x[0] for x in ticks]
            states = [x[1] for x in ticks]
            stamps = runs(ns)  # the timestamps' bytes, once for every channel
            put = self._put_js
            if all(s.effort is not None for s in states):
                msgs = self._js_full.encode_many(ns, np.array([(s.q, s.dq, s.effort) for s in states]), stamps)
            elif all(s.effort is None for s in states):
                msgs = self._js_noeff.encode_many(ns, np.array([(s.q, s.dq) for s in states]), stamps)
            else:
                msgs = [self._js_noeff.encode(n, (s.q, s.dq)) if s.effort is None else
                        self._js_full.encode(n, (s.q, s.dq, s.effort)) for n, s in zip(ns, states, strict=True)]
            for n, m in zip(ns, msgs, strict=True):
                put(n, m)
            if self._put_tf is not None:
                posed = [(n, v) for n, _, v in ticks if v is not None]
                if posed:
                    put = self._put_tf
                    at = [n for n, _ in posed]
                    msgs = self._tf.encode_many(at, np.array([v for _, v in posed]),
                                                stamps if len(at) == len(ns) else None)
                    for n, m in zip(at, msgs, strict=True):
                        put(n, m)
            self._state_json(ns, states)
        if cmds:
            self._cmds = []
            at = [n for n, _ in cmds]
            put = self._put_jc
            same = ticks and at == ns  # commands logged with their states (the loop): their timestamps are made
            msgs = self._jc.encode_many(at, np.array([q for _, q in cmds])[:, None, :], stamps if same else None)
            for n, m in zip(at, msgs, strict=True):
                put(n, m)
        if times:
            self._times = []
            if self._put_timing is None:
                self._put_timing = self.channel("/timing", TIMING.schema, "protobuf")
            put = self._put_timing
            for (n, _), m in zip(times, TIMING.encode_many(np.array([[c * 1e3] for _, c in times], dtype=float)),
                                 strict=True):
                put(n, m)
        super()._write_pending()

    def _state_json(self, ns: list[int], states: list[State]) -> None:
        """``/imu``, ``/contacts``, ``/base`` (felis Protobuf, `felis.logs.messages`: one scatter per channel) and
        ``/faults`` (JSON, when they change) of deferred states, where each state has them."""
        imus = [(n, s.imu) for n, s in zip(ns, states, strict=True) if s.imu is not None]
        if imus:
            quat = np.array([i.quat for _, i in imus], dtype=float).reshape(-1, 4)  # (w, x, y, z)
            x, y = quat[:, 1], quat[:, 2]
            with np.errstate(invalid="ignore"):
                tilt = np.degrees(np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))
            v = np.concatenate([quat[:, 1:], quat[:, :1], np.array([i.gyro for _, i in imus], dtype=float),
                                np.array([i.accel for _, i in imus], dtype=float), tilt[:, None]], axis=1)
            if self._put_imu is None:
                self._put_imu = self.channel("/imu", IMU.schema, "protobuf")
            put = self._put_imu
            for (n, _), m in zip(imus, IMU.encode_many(v), strict=True):
                put(n, m)
        nf = len(self._feet)
        cs = [(n, s.contacts) for n, s in zip(ns, states, strict=True)
              if s.contacts is not None and len(s.contacts) == nf]
        if cs and nf:
            if self._put_contacts is None:
                self._put_contacts = self.channel("/contacts", self._contacts_msg.schema, "protobuf")
            put = self._put_contacts
            flags = np.array([c for _, c in cs], dtype=bool)
            for (n, _), m in zip(cs, self._contacts_msg.encode_many(None, flags), strict=True):
                put(n, m)
        hs = [(n, s.height) for n, s in zip(ns, states, strict=True) if s.height is not None]
        if hs:
            if self._put_base is None:
                self._put_base = self.channel("/base", BASE.schema, "protobuf")
            put = self._put_base
            for (n, _), m in zip(hs, BASE.encode_many(np.array([[h] for _, h in hs], dtype=float)), strict=True):
                put(n, m)
        for n, s in zip(ns, states, strict=True):
            f = s.faults
            if f is not None and f is not self._faults_seen:  # the same object: unchanged (the simulation's)
                self._faults_seen = f
                self._faults(n, f)

    def _faults(self, ns: int, f) -> None:
        hw, stale = np.asarray(f.hardware), f.stale
        key = (hw.tobytes(), f.comm_errors, None if stale is None else np.asarray(stale).tobytes())
        if key != self._last_faults:
            self._last_faults = key
            text = _text({"hardware": [int(v) for v in hw.tolist()], "comm_errors": int(f.comm_errors),
                          **({} if stale is None else {"stale": np.asarray(stale, dtype=bool).tolist()})})
            if self._put_faults is None:
                self._put_faults = self.channel("/faults", FAULTS_SCHEMA)
            self._put_faults(ns, text)

    def tick(self, state: State, command: Command, control_s: float) -> None:
        """One loop tick in one call (what `felis.loop.run_loop` uses): `state`, `command` at the state's time,
        `timing`."""
        self.state(state)
        ns = self._ticks[-1][0]
        self._cmds.append((ns, command.q))
        self._times.append((ns, control_s))

    def command(self, t: float, command: Command) -> None:
        """Log the command actually sent at time ``t`` on ``/joint_commands``."""
        self._check_open()
        self._cmds.append((self.ns(t), command.q))

    def timing(self, t: float, control_s: float) -> None:
        """Log the tick's control-path time on ``/timing``."""
        self._times.append((self.ns(t), control_s))

    def event(self, t: float, kind: str, **detail) -> None:
        """Log a discrete event (safety clamp, watchdog trip, comm lost, …) on ``/log`` (foxglove.Log)."""
        self._check_open()
        self._event(t, kind, jsonable(detail))

    def _event(self, t: float, kind: str, detail: dict) -> None:
        ns = self.ns(t)
        self._tick(ns)
        d = detail
        text = str(kind) + (" " + json.dumps(d, separators=(",", ":"), ensure_ascii=False) if d else "")
        msg = Log(timestamp=_stamp(ns), level=_LEVEL.get(str(kind), LogLevel.Info), message=text, name=str(kind))
        self._put_log(ns, msg.encode())

    def __enter__(self) -> RunLog:
        return self


def scene_update(scene: RobotScene, ns: int) -> SceneUpdate:
    """The robot's geoms as a ``foxglove.SceneUpdate``: one entity per body (frame-locked to the body's frame),
    one for the world's geoms (the floor) and the path (orange line), in frame ``world``."""
    stamp = _stamp(ns)
    per: dict[int, dict[str, list]] = {}
    for g in scene.geoms:
        prims = per.setdefault(g.body, {"cubes": [], "spheres": [], "cylinders": []})
        w, x, y, z = g.quat
        rot = Quaternion(x=x, y=y, z=z, w=w)
        pose = Pose(position=Vector3(x=g.pos[0], y=g.pos[1], z=g.pos[2]), orientation=rot)
        color = Color(r=g.rgba[0], g=g.rgba[1], b=g.rgba[2], a=g.rgba[3])
        sx, sy, sz = g.size
        if g.shape == "box":
            prims["cubes"].append(CubePrimitive(pose=pose, size=Vector3(x=2 * sx, y=2 * sy, z=2 * sz), color=color))
        elif g.shape == "plane":
            hx, hy = (sx or 10.0), (sy or 10.0)
            p = Pose(position=Vector3(x=g.pos[0], y=g.pos[1], z=g.pos[2] - 0.0005), orientation=rot)
            prims["cubes"].append(CubePrimitive(pose=p, size=Vector3(x=2 * hx, y=2 * hy, z=0.001), color=color))
        elif g.shape == "sphere":
            prims["spheres"].append(SpherePrimitive(pose=pose, size=Vector3(x=2 * sx, y=2 * sx, z=2 * sx),
                                                    color=color))
        elif g.shape == "ellipsoid":
            prims["spheres"].append(SpherePrimitive(pose=pose, size=Vector3(x=2 * sx, y=2 * sy, z=2 * sz),
                                                    color=color))
        elif g.shape in ("cylinder", "capsule"):
            prims["cylinders"].append(CylinderPrimitive(pose=pose, size=Vector3(x=2 * sx, y=2 * sx, z=2 * sy),
                                                        bottom_scale=1.0, top_scale=1.0, color=color))
            if g.shape == "capsule":  # the two caps: spheres at ±half length along the geom's z
                axis = _rotate((w, x, y, z), (0.0, 0.0, sy))
                for sign in (1.0, -1.0):
                    c = Pose(position=Vector3(x=g.pos[0] + sign * axis[0], y=g.pos[1] + sign * axis[1],
                                              z=g.pos[2] + sign * axis[2]), orientation=rot)
                    prims["spheres"].append(SpherePrimitive(pose=c, size=Vector3(x=2 * sx, y=2 * sx, z=2 * sx),
                                                            color=color))
    entities = []
    for b, prims in per.items():
        frame = "world" if b < 0 else scene.bodies[b]
        entities.append(SceneEntity(timestamp=stamp, frame_id=frame, id=f"geoms/{frame}", frame_locked=b >= 0,
                                    **prims))
    if scene.path is not None and len(scene.path) > 1:
        pts = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in scene.path]
        line = LinePrimitive(pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)), thickness=0.004,
                             points=pts, color=Color(r=1.0, g=0.55, b=0.1, a=0.9))
        entities.append(SceneEntity(timestamp=stamp, frame_id="world", id="target_path", lines=[line]))
    return SceneUpdate(entities=entities)


def _rotate(q, v):
    w, x, y, z = q
    vx, vy, vz = v
    # v' = v + 2w (u × v) + 2 u × (u × v), u = (x, y, z)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    dx, dy, dz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return vx + 2 * (w * cx + dx), vy + 2 * (w * cy + dy), vz + 2 * (w * cz + dz)


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
    except (McapError, struct.error, UnicodeDecodeError, ValueError, RuntimeError):
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
