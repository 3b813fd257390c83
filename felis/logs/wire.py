"""Protobuf bytes of Foxglove's per-tick messages (``foxglove.FrameTransforms``, ``foxglove.JointStates``) from
a template laid out once: only numbers change from tick to tick.

Why: building the SDK's message objects costs about 2 µs per body (a ``FrameTransform`` with its ``Vector3``,
``Quaternion`` and ``Timestamp``), 45 µs a tick for the cat's bodies, most of a tick's logging budget. The wire
format of these messages is fixed once the names are known: every number is a ``double`` (wire type 1,
8 bytes little-endian) and the one variable-length part, the ``google.protobuf.Timestamp``, is the same for
every element of one message. So a message is a template with the names in place, into which each tick
writes the doubles (one numpy scatter) and the timestamp bytes (one template per timestamp length, five at
most). The bytes are canonical protobuf except that fields equal to 0.0 are written rather than omitted
(allowed: a decoder reads them the same); ``tests/logs`` decodes them with the protobuf runtime and compares
them with the SDK's own encoding of the same values.

Field numbers (from the SDK's schemas, ``foxglove.messages.X.get_schema()``)::

    FrameTransforms  1: repeated FrameTransform transforms
    FrameTransform   1: Timestamp timestamp  2: string parent_frame_id  3: string child_frame_id
                     4: Vector3 translation  5: Quaternion rotation
    Vector3          1: x  2: y  3: z                 Quaternion 1: x  2: y  3: z  4: w   (all double)
    JointStates      1: Timestamp timestamp  2: repeated JointState joints
    JointState       1: string name  2: position  3: velocity  4: acceleration  5: effort (optional doubles)
    Timestamp        1: int64 seconds  2: int32 nanos
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


_last_stamp: list = [None, b""]  # one-entry cache: a tick's messages share their time
_last_sec: list = [None, b""]


def timestamp(ns: int) -> bytes:
    """The body of a ``google.protobuf.Timestamp`` for ``ns`` nanoseconds since the epoch (nanos always
    written, so the length depends only on the size of the numbers)."""
    if ns == _last_stamp[0]:
        return _last_stamp[1]
    sec, nsec = divmod(int(ns), 1_000_000_000)
    if sec != _last_sec[0]:
        _last_sec[0], _last_sec[1] = sec, b"\x08" + varint(sec) + b"\x10"
    out = _last_sec[1] + varint(nsec)
    _last_stamp[0], _last_stamp[1] = ns, out
    return out


class _Slot:
    """A placeholder of ``size`` bytes in a template: a double (8) or the timestamp body."""

    __slots__ = ("kind", "size")

    def __init__(self, kind: str, size: int):
        self.kind, self.size = kind, size


class _Msg:
    """A message under construction: bytes and slots, with nested lengths known (slots have fixed sizes)."""

    def __init__(self):
        self.parts: list[bytes | _Slot] = []

    def __len__(self) -> int:
        return sum(p.size if isinstance(p, _Slot) else len(p) for p in self.parts)

    def double(self, field: int) -> _Msg:
        self.parts += [varint(field << 3 | 1), _Slot("d", 8)]
        return self

    def boolean(self, field: int) -> _Msg:
        self.parts += [varint(field << 3 | 0), _Slot("b", 1)]
        return self

    def string(self, field: int, text: str) -> _Msg:
        raw = text.encode()
        self.parts += [varint(field << 3 | 2) + varint(len(raw)) + raw]
        return self

    def message(self, field: int, sub: _Msg) -> _Msg:
        self.parts += [varint(field << 3 | 2) + varint(len(sub)), *sub.parts]
        return self

    def stamp(self, field: int, size: int) -> _Msg:
        self.parts += [varint(field << 3 | 2) + varint(size), _Slot("t", size)]
        return self


class _Template:
    """A compiled message: the bytes, where the doubles start (one offset each), where the timestamp bodies and the
    booleans go. Compiled once per layout (`_compiled`) and shared by every encoder of that layout; the scratch
    buffers are kept per thread and per power of two of the batch size, so a log opened per episode finds them
    ready (building one per batch size was a sixth of a short episode's logging).

    Filling writes whole values, not bytes: the buffer is seen through a window view with a one-byte stride
    (``dtype`` u8 for the doubles' bits, V<size> for the timestamps), so one fancy-index assignment puts every
    double of K messages in place (the view's items overlap; the slots written never do)."""

    def __init__(self, msg: _Msg, stamp_size: int):
        raw, slots = bytearray(), {"d": [], "t": [], "b": []}
        for p in msg.parts:
            if isinstance(p, _Slot):
                slots[p.kind].append(len(raw))
                raw += bytes(p.size)
            else:
                raw += p
        self.base = np.frombuffer(bytes(raw), dtype=np.uint8).copy()
        self.doubles = np.array(slots["d"], dtype=np.intp)  # start of each double
        self.stamps = np.array(slots["t"], dtype=np.intp)  # start of each timestamp body
        self.bools = np.array(slots["b"], dtype=np.intp)
        self.stamp_size = stamp_size
        self.n_stamps = len(slots["t"])
        # (thread, K) → (scratch for K messages, its windows, the slots of K messages)
        self._many: dict[tuple[int, int], tuple] = {}

    def _scratch(self, k: int) -> tuple:
        """Scratch for up to the next power of two ≥ ``k`` messages (a handful of sizes, whatever batches come)."""
        cap = 1 << max(0, (k - 1).bit_length())
        key = (threading.get_ident(), cap)
        many = self._many.get(key)
        if many is None:
            if len(self._many) >= 256:  # many threads: keep it bounded (a thread's own stay valid)
                self._many = {}
            n = len(self.base)
            off = (np.arange(cap, dtype=np.intp) * n)[:, None]
            buf = np.tile(self.base, cap)
            u8 = np.ndarray(shape=(max(len(buf) - 7, 0),), dtype="<u8", buffer=buf, strides=(1,))
            size = max(self.stamp_size, 1)
            ts = np.ndarray(shape=(max(len(buf) - size + 1, 0),), dtype=f"V{size}", buffer=buf, strides=(1,))
            many = self._many[key] = (buf, u8, ts, (self.doubles[None, :] + off).reshape(-1),
                                      (self.stamps[None, :] + off).reshape(-1), (self.bools[None, :] + off).reshape(-1))
        return many

    def fill(self, values: np.ndarray, stamp: bytes) -> bytes:
        """``values``: a C-contiguous float64 array with the doubles in template order."""
        return self.fill_many(values.reshape(1, -1), [stamp] if self.n_stamps else None)[0]

    def fill_many(self, values: np.ndarray, stamps: Sequence[bytes] | None = None,
                  flags: np.ndarray | None = None) -> list[bytes]:
        """K messages at once (one scatter for all): ``values`` (K, doubles) C-contiguous float64, ``stamps``
        the K timestamp bodies, each of this template's size (None: a template without a timestamp), ``flags``
        (K, booleans) for a template with boolean fields."""
        k = len(values)
        buf, u8, ts, dbl, tsi, bi = self._scratch(k)  # index arrays are message by message: the first k's
        nd, nb, n = len(self.doubles), len(self.bools), len(self.base)
        if nd:
            u8[dbl[:k * nd]] = values.view("<u8").reshape(-1)
        if nb:
            buf[bi[:k * nb]] = np.asarray(flags, dtype=bool).reshape(-1)
        if self.n_stamps:
            ts[tsi[:k * self.n_stamps]] = np.repeat(np.frombuffer(b"".join(stamps), dtype=ts.dtype), self.n_stamps)
        raw = buf[:k * n].tobytes()
        return [raw[i * n:(i + 1) * n] for i in range(k)]


def runs(ns: Sequence[int]) -> list[tuple[int, int, list[bytes]]]:
    """The timestamp bodies of ``ns`` in runs of one length: (start, stop, bodies) — a batch of ticks has one run,
    now and then two (the nanoseconds' varint grows past 2²¹ and 2²⁸ within each second)."""
    stamps = [timestamp(x) for x in ns]
    out, i = [], 0
    while i < len(stamps):
        size, j = len(stamps[i]), i + 1
        while j < len(stamps) and len(stamps[j]) == size:
            j += 1
        out.append((i, j, stamps[i:j]))
        i = j
    return out


_COMPILED: dict[tuple, _Template] = {}  # layout key → template: a log opened per episode reuses them


def _compiled(key: tuple, build) -> _Template:
    """The template of layout ``key`` (built by ``build()`` the first time; shared, see `_Template`)."""
    t = _COMPILED.get(key)
    if t is None:
        if len(_COMPILED) > 256:  # many robots in one process: keep the cache bounded
            _COMPILED.clear()
        t = _COMPILED[key] = build()
    return t


class FrameTransformsEncoder:
    """``foxglove.FrameTransforms``: every child frame's pose in ``parent``, one timestamp for all.

    ``encode(ns, values)``: values (n, 7) = translation x, y, z and rotation x, y, z, w per child.
    """

    def __init__(self, children: Sequence[str], parent: str = "world"):
        self.children, self.parent = tuple(children), parent
        self._templates: dict[int, _Template] = {}

    def _template(self, size: int) -> _Template:
        t = self._templates.get(size)
        if t is None:
            def build() -> _Template:
                top = _Msg()
                for child in self.children:
                    tf = _Msg().stamp(1, size).string(2, self.parent).string(3, child)
                    tf.message(4, _Msg().double(1).double(2).double(3))
                    tf.message(5, _Msg().double(1).double(2).double(3).double(4))
                    top.message(1, tf)
                return _Template(top, size)

            t = self._templates[size] = _compiled(("tf", self.parent, self.children, size), build)
        return t

    def encode(self, ns: int, values: np.ndarray) -> bytes:
        stamp = timestamp(ns)
        return self._template(len(stamp)).fill(np.ascontiguousarray(values, dtype=float), stamp)

    def encode_many(self, ns: Sequence[int], values: np.ndarray, stamp_runs=None) -> list[bytes]:
        """Messages at the times ``ns`` from values (K, n, 7): `encode` of each, in one scatter per run of
        timestamps of one length (``stamp_runs``: `runs` of ``ns``, when the caller has them)."""
        v = np.ascontiguousarray(values, dtype=float).reshape(len(ns), -1)
        out: list[bytes] = []
        for i, j, stamps in stamp_runs or runs(ns):
            out += self._template(len(stamps[0])).fill_many(v[i:j], stamps)
        return out


class JointStatesEncoder:
    """``foxglove.JointStates``: per joint its name and the doubles of ``fields`` (a subset of position,
    velocity, effort, in that order); ``encode(ns, values)`` with values (len(fields), n_joints)."""

    FIELD = {"position": 2, "velocity": 3, "acceleration": 4, "effort": 5}

    def __init__(self, names: Sequence[str], fields: Sequence[str] = ("position", "velocity", "effort")):
        self.names, self.fields = tuple(names), tuple(fields)
        self._templates: dict[int, _Template] = {}
        self._values = np.zeros((len(self.names), len(self.fields)))

    def _template(self, size: int) -> _Template:
        t = self._templates.get(size)
        if t is None:
            def build() -> _Template:
                top = _Msg().stamp(1, size)
                for name in self.names:
                    js = _Msg().string(1, name)
                    for f in self.fields:
                        js.double(self.FIELD[f])
                    top.message(2, js)
                return _Template(top, size)

            t = self._templates[size] = _compiled(("js", self.names, self.fields, size), build)
        return t

    def encode(self, ns: int, values) -> bytes:
        stamp = timestamp(ns)
        v = self._values  # doubles go joint by joint: (fields, joints) -> (joints, fields)
        for k, col in enumerate(values):
            v[:, k] = col
        return self._template(len(stamp)).fill(v, stamp)

    def encode_many(self, ns: Sequence[int], values: np.ndarray, stamp_runs=None) -> list[bytes]:
        """Messages at the times ``ns`` from values (K, len(fields), n_joints): `encode` of each, in one
        scatter per run of timestamps of one length (``stamp_runs``: `runs` of ``ns``, when the caller has them)."""
        v = np.ascontiguousarray(np.asarray(values, dtype=float).transpose(0, 2, 1)).reshape(len(ns), -1)
        out: list[bytes] = []
        for i, j, stamps in stamp_runs or runs(ns):
            out += self._template(len(stamps[0])).fill_many(v[i:j], stamps)
        return out
