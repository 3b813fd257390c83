"""felis's own per-tick messages (``/imu``, ``/contacts``, ``/base``, ``/timing``) in Protobuf: schemas and encoders.

Why Protobuf and not JSON: formatting these four channels as JSON text was 40 % of a run log's cost (``python
bench/sim_speed.py --with-log``). As Protobuf messages of fixed layout they are filled from templates like
Foxglove's own per-tick messages (`felis.logs.wire`): one numpy scatter per channel for a chunk's ticks. Every
viewer that reads Foxglove's Protobuf schemas reads them (the schema travels in the file as a FileDescriptorSet),
and a plot path is the same as it was in JSON (``/imu.tilt_deg``, ``/contacts.fl_foot``).

The messages (package ``felis``, proto3; every field written, zeros included; NaN is a valid double)::

    message Vector3    { double x = 1; double y = 2; double z = 3; }
    message Quaternion { double x = 1; double y = 2; double z = 3; double w = 4; }
    message Imu        { Quaternion orientation = 1;        // the IMU's orientation in the world
                         Vector3 angular_velocity = 2;      // rad/s, IMU frame
                         Vector3 linear_acceleration = 3;   // m/s², IMU frame
                         double tilt_deg = 4; }             // body up axis against world up
    message Contacts   { bool <foot> = 1; … }               // one field per foot of the robot, by name
    message Base       { double height = 1; }               // m, the robot's reference site above the floor
    message Timing     { double control_ms = 1; }           // read → compute → safety → write, this tick

`as_dict` turns a decoded message back into the dict the JSON form had (what `felis.logs.reader.read_log` reads).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence

import foxglove
import numpy as np
from google.protobuf import descriptor_pb2

from felis.logs.wire import _Msg, _Template

_D = descriptor_pb2.FieldDescriptorProto
_SUB = {"Vector3": ("x", "y", "z"), "Quaternion": ("x", "y", "z", "w")}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class FelisMessage:
    """One flat felis message: ``fields`` is a sequence of (name, kind) with kind ``double``, ``bool``,
    ``Vector3`` or ``Quaternion``, in field-number order. ``schema`` is its `foxglove.Schema` (protobuf);
    `encode_many` gives the bytes of K messages from their doubles (K, `n_doubles`, in field order, x y z (w) for
    the nested ones) and booleans (K, `n_bools`)."""

    def __init__(self, name: str, fields: Sequence[tuple[str, str]]):
        for f, kind in fields:
            if not _NAME.match(f):
                raise ValueError(f"felis.{name}: field name {f!r} is not an identifier (letters, digits, _)")
            if kind not in ("double", "bool", *_SUB):
                raise ValueError(f"felis.{name}: unknown field kind {kind!r}")
        self.name, self.fields = f"felis.{name}", tuple(fields)
        file = descriptor_pb2.FileDescriptorProto(name=f"felis/{name}.proto", package="felis", syntax="proto3")
        for sub in sorted({k for _, k in self.fields if k in _SUB}):
            m = file.message_type.add(name=sub)
            for i, axis in enumerate(_SUB[sub], 1):
                m.field.add(name=axis, number=i, type=_D.TYPE_DOUBLE, label=_D.LABEL_OPTIONAL)
        top, msg = file.message_type.add(name=name), _Msg()
        for i, (f, kind) in enumerate(self.fields, 1):
            if kind == "double":
                top.field.add(name=f, number=i, type=_D.TYPE_DOUBLE, label=_D.LABEL_OPTIONAL)
                msg.double(i)
            elif kind == "bool":
                top.field.add(name=f, number=i, type=_D.TYPE_BOOL, label=_D.LABEL_OPTIONAL)
                msg.boolean(i)
            else:
                top.field.add(name=f, number=i, type=_D.TYPE_MESSAGE, label=_D.LABEL_OPTIONAL,
                              type_name=f".felis.{kind}")
                sub = _Msg()
                for j in range(1, len(_SUB[kind]) + 1):
                    sub.double(j)
                msg.message(i, sub)
        data = descriptor_pb2.FileDescriptorSet(file=[file]).SerializeToString()
        self.schema = foxglove.Schema(name=self.name, encoding="protobuf", data=data)
        self._template = _Template(msg, 0)
        self.n_doubles = len(self._template.doubles)
        self.n_bools = len(self._template.bools)

    def encode_many(self, values: np.ndarray | None = None, flags: np.ndarray | None = None) -> list[bytes]:
        k = len(values) if values is not None else len(flags)
        v = np.ascontiguousarray(np.zeros((k, 0)) if values is None else values, dtype=float).reshape(k, -1)
        return self._template.fill_many(v, None, flags)


IMU = FelisMessage("Imu", (("orientation", "Quaternion"), ("angular_velocity", "Vector3"),
                           ("linear_acceleration", "Vector3"), ("tilt_deg", "double")))
BASE = FelisMessage("Base", (("height", "double"),))
TIMING = FelisMessage("Timing", (("control_ms", "double"),))


def contacts_message(feet: Sequence[str]) -> FelisMessage:
    """``felis.Contacts`` for these feet: one boolean field per foot, by name (built once per set of feet: a log
    opened per episode reuses it)."""
    return _contacts(tuple(str(f) for f in feet))


@functools.lru_cache(maxsize=32)
def _contacts(feet: tuple[str, ...]) -> FelisMessage:
    return FelisMessage("Contacts", tuple((f, "bool") for f in feet))


def as_dict(msg) -> dict:
    """A decoded felis message as the dict of its fields (nested messages as dicts), every field present."""
    out = {}
    for f in msg.DESCRIPTOR.fields:
        v = getattr(msg, f.name)
        out[f.name] = as_dict(v) if f.message_type is not None else v
    return out
