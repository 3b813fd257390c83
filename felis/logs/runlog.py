"""Run logs: one control run written to an MCAP file through the Foxglove SDK (`felis.logs.mcap.McapLog`), with
Foxglove's well-known schemas; read back by `felis.logs.reader`.

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
the body poses copied; `RunLog.tick` costs one comparison, the poses and one append between chunk boundaries) until
the chunk is finished, at most `FLUSH_S` of run time later, and then encoded all together, channel by channel: the
Protobuf ones of all the kept ticks filled into templates in one numpy scatter per channel (`felis.logs.wire`,
`felis.logs.messages`). Done together they cost less than one tick at a time between physics steps, which evict the
interpreter's working set from the CPU caches; the per-tick channels are all Protobuf because formatting four of
them as JSON text was 40 % of the log's cost. The encoding, writing and finishing of a chunk run on a writer thread
(`felis.logs.background`) while the loop's thread waits in the physics step or its sleep, when the run keeps pace
with the clock; a simulation more than `felis.logs.mcap.FAST` times faster than real time never waits, and there
the writer only competes with it for the interpreter and the CPU, so it finishes its chunks itself
(`McapLog._boundary`). A `State` and a `Command` are therefore not to be changed after they are logged (the
robots make new ones each tick). The live view gets them in the same batches: a viewer sees a run at most
2 × `FLUSH_S` plus a tick late. Events (``/log``) and messages are written at once.

Crash safety: the file is chunked (lz4) and indexed. At the start of the first tick by which both `FLUSH_S` of run
time and `FLUSH_WALL_S` (half of it) of wall time have passed since the last, the chunk's ticks go to the writer
thread, which writes them, finishes the chunk and hands it to the operating system; the chunk handed over before is
written first if the writer has not finished it, so at most one handed-over chunk is ever unwritten (a run more
than `FAST` times faster than real time does this on its own thread: nothing is left with a writer). A process
killed mid-run therefore loses at most the last 2 × `FLUSH_S` plus two ticks (0.1 s at 100 Hz) of a run that keeps
pace with the clock (hardware, servo-in-the-loop, a real-time simulation), and a simulation running faster than
real time at most the ticks of its last 2 × `FLUSH_WALL_S` of wall time, plus two, plus two × `FLUSH_S` / 4 of
run time (the chunk boundary is looked for at least that often, or every quarter of the run time since the last
chunk, which in a fast simulation is about a quarter of `FLUSH_WALL_S` of wall time). Finishing a chunk costs about
half a millisecond whatever it holds (on the writer thread).
`felis.logs.reader.read_log` walks the records of the intact prefix
and reports ``complete=False`` for a cut file. (No ``fsync``: a power cut may lose the page cache.)

``--live``: the same channels go to a `felis.logs.live.LiveView` (Foxglove WebSocket server), if one is given.
"""


from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
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
    Vector3,
)

from felis.hal import Command, State
from felis.logs.mcap import McapLog, _stamp
from felis.logs.messages import BASE, IMU, TIMING, contacts_message
from felis.logs.schemas import FAULTS_SCHEMA, _text, jsonable
from felis.logs.wire import FrameTransformsEncoder, JointStatesEncoder, runs
from felis.scene import BodyPoses, RobotScene
from felis.spec import RobotSpec

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
        self._rows: list[tuple] = []  # deferred ticks (`tick`): (t, state, q sent, control s, poses)
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
        self._ticks.append((ns, state, None if self._poses is None else self._poses(state)))

    def _take(self):
        rows, ticks, cmds, times = self._rows, self._ticks, self._cmds, self._times
        self._rows, self._ticks, self._cmds, self._times = [], [], [], []
        if rows:
            self._last_ns = max(self._last_ns, self.ns(rows[-1][0]))
        return rows, ticks, cmds, times, super()._take()

    def _ns_many(self, t: list[float]) -> list[int]:
        """`ns` of many run times at once (the same integers; times past 1e9 s, beyond int64 once in ns, one by
        one through `ns`)."""
        a = np.array(t, dtype=float)
        ok = np.isfinite(a) & (a > 0) & (a < 1e9)
        out = (self.start_ns + np.where(ok, np.rint(np.where(ok, a, 0.0) * 1e9), 0.0).astype(np.int64)).tolist()
        for i in np.flatnonzero(np.isfinite(a) & (a >= 1e9)):
            out[i] = self.ns(float(a[i]))
        return out

    def _merge(self, rows: list[tuple], ticks: list[tuple], cmds: list[tuple], times: list[tuple]):
        """The ticks of `tick` (rows) and of `state`, `command`, `timing` as (ns, …) lists, in time order."""
        ns = self._ns_many([r[0] for r in rows])
        t2 = [(n, r[1], r[4]) for n, r in zip(ns, rows, strict=True)]
        c2 = [(n, r[2]) for n, r in zip(ns, rows, strict=True)]
        m2 = [(n, r[3]) for n, r in zip(ns, rows, strict=True)]
        out = []
        for a, b in ((t2, ticks), (c2, cmds), (m2, times)):
            if b:
                a = sorted(a + b, key=lambda x: x[0])
            out.append(a)
        return out

    def _steps(self, data) -> Iterator[None]:
        """The deferred ticks, channel by channel: the Protobuf ones of all the ticks in one scatter each
        (`felis.logs.wire`), then the JSON ones tick by tick, then the other deferred writes; a slice (``yield``)
        is one channel's encoding or `SLICE` messages (`felis.logs.background`)."""
        rows, ticks, cmds, times, rest = data
        if rows:
            ticks, cmds, times = self._merge(rows, ticks, cmds, times)
        ns = stamps = None
        if ticks:
            ns = [x[0] for x in ticks]
            states = [x[1] for x in ticks]
            stamps = runs(ns)  # the timestamps' bytes, once for every channel
            if all(s.effort is not None for s in states):
                msgs = self._js_full.encode_many(ns, np.array([(s.q, s.dq, s.effort) for s in states]), stamps)
            elif all(s.effort is None for s in states):
                msgs = self._js_noeff.encode_many(ns, np.array([(s.q, s.dq) for s in states]), stamps)
            else:
                msgs = [self._js_noeff.encode(n, (s.q, s.dq)) if s.effort is None else
                        self._js_full.encode(n, (s.q, s.dq, s.effort)) for n, s in zip(ns, states, strict=True)]
            yield
            yield from _sliced(self._put_js, ns, msgs)
            if self._put_tf is not None:
                posed = [(n, v) for n, _, v in ticks if v is not None]
                if posed:
                    at = [n for n, _ in posed]
                    msgs = self._tf.encode_many(at, np.array([v for _, v in posed]),
                                                stamps if len(at) == len(ns) else None)
                    yield
                    yield from _sliced(self._put_tf, at, msgs)
            yield from self._state_json(ns, states)
        if cmds:
            at = [n for n, _ in cmds]
            same = ticks and at == ns  # commands logged with their states (the loop): their timestamps are made
            msgs = self._jc.encode_many(at, np.array([q for _, q in cmds])[:, None, :], stamps if same else None)
            yield
            yield from _sliced(self._put_jc, at, msgs)
        if times:
            if self._put_timing is None:
                self._put_timing = self.channel("/timing", TIMING.schema, "protobuf")
            msgs = TIMING.encode_many(np.array([[c * 1e3] for _, c in times], dtype=float))
            yield
            yield from _sliced(self._put_timing, [n for n, _ in times], msgs)
        yield from super()._steps(rest)

    def _state_json(self, ns: list[int], states: list[State]) -> Iterator[None]:
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
            msgs = IMU.encode_many(v)
            yield
            yield from _sliced(self._put_imu, [n for n, _ in imus], msgs)
        nf = len(self._feet)
        cs = [(n, s.contacts) for n, s in zip(ns, states, strict=True)
              if s.contacts is not None and len(s.contacts) == nf]
        if cs and nf:
            if self._put_contacts is None:
                self._put_contacts = self.channel("/contacts", self._contacts_msg.schema, "protobuf")
            flags = np.array([c for _, c in cs], dtype=bool)
            msgs = self._contacts_msg.encode_many(None, flags)
            yield
            yield from _sliced(self._put_contacts, [n for n, _ in cs], msgs)
        hs = [(n, s.height) for n, s in zip(ns, states, strict=True) if s.height is not None]
        if hs:
            if self._put_base is None:
                self._put_base = self.channel("/base", BASE.schema, "protobuf")
            msgs = BASE.encode_many(np.array([[h] for _, h in hs], dtype=float))
            yield
            yield from _sliced(self._put_base, [n for n, _ in hs], msgs)
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
        `timing`. Kept as it comes (the log times are made with the encoding); between chunk boundaries a tick
        costs one comparison, the body poses and one append."""
        t = state.t
        if not t < self._next_t or self._closed:  # a boundary (or a NaN time, or closed): the general path
            self._check_open()
            self._tick(self.ns(t))
        poses = self._poses
        self._rows.append((t, state, command.q, control_s, None if poses is None else poses(state)))
        bg = self._bg
        if bg is not None and bg._jobs:
            bg.nudge()

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


SLICE = 24  # messages a slice of the writer logs (each `Channel.log` ~2 µs)


def _sliced(put, ns: list[int], msgs: list[bytes]) -> Iterator[None]:
    """``put.many`` in slices of `SLICE` messages, yielding after each."""
    for i in range(0, len(msgs), SLICE):
        put.many(ns[i:i + SLICE], msgs[i:i + SLICE])
        yield


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


