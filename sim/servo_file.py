"""Servo parameter files: per-joint `ServoParams` for the MuJoCo backend, as `felis sysid` writes them.

Format (JSON, SI units in joint coordinates: rad, or m for a prismatic joint)::

    {"schema": 1, "robot": "cat",
     "joints": {"fl_pitch": {"kp": 1.66, "torque_limit": 0.41, "damping": 0.034,
                             "armature": 0.001, "frictionloss": 0.0075}, ...},
     "fit": {...}}                      # optional: how the numbers were obtained (free-form)

Joints not listed keep the datasheet model (`felis.sim.servo.servo_params`). Loading checks
everything and raises `ServoParamsError` with one line naming the file and the problem: a missing or
unreadable file, bad JSON, another schema or robot, an unknown joint, a missing or extra field, a
non-finite or negative value (``kp`` and ``torque_limit`` must be positive). Writing is atomic: a
temporary file in the same folder, then ``os.replace``, so a crash never leaves half a file.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import asdict, fields
from pathlib import Path

from felis.errors import ServoParamsError
from felis.files import check_fields, read_text, write_atomic
from felis.sim.servo import ServoParams
from felis.spec import RobotSpec

SCHEMA = 1
FIELDS = tuple(f.name for f in fields(ServoParams))
_POSITIVE = ("kp", "torque_limit")


def servo_params_dict(params: Mapping[str, ServoParams]) -> dict[str, dict[str, float]]:
    """``{joint: {field: value}}``, the file's ``joints`` object."""
    return {name: {k: float(v) for k, v in asdict(p).items()} for name, p in params.items()}


def save_servo_params(path: str | os.PathLike, robot: str, params: Mapping[str, ServoParams],
                      fit: Mapping | None = None) -> Path:
    """Write ``params`` for ``robot`` to ``path`` atomically; returns the path.

    ``fit`` (optional, JSON-serialisable) records how the parameters were obtained.
    """
    path = Path(path)
    for name, p in params.items():
        _check_joint(path, name, asdict(p))
    doc = {"schema": SCHEMA, "robot": robot, "joints": servo_params_dict(params)}
    if fit is not None:
        doc["fit"] = dict(fit)
    try:
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as e:
        raise ServoParamsError(f"cannot write servo parameters {path}: {e}") from None
    write_atomic(path, text, "servo parameters", ServoParamsError)
    return path


def load_servo_params(path: str | os.PathLike, spec: RobotSpec) -> dict[str, ServoParams]:
    """Read a servo parameter file for ``spec``'s robot: ``{joint: ServoParams}`` (module doc)."""
    path = Path(path)
    text = read_text(path, "servo parameter file", ServoParamsError, hint=" (make one with `felis sysid`)",
                     directory=None, unreadable="{path}: cannot read: {reason}")
    try:
        doc = json.loads(text, parse_constant=lambda c: float("nan"))
    except json.JSONDecodeError as e:
        raise ServoParamsError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    if not isinstance(doc, dict):
        raise ServoParamsError(f"{path}: expected a JSON object with schema, robot and joints")
    if doc.get("schema") != SCHEMA:
        raise ServoParamsError(f"{path}: schema {doc.get('schema')!r} is not supported (expected {SCHEMA})")
    if doc.get("robot") != spec.name:
        raise ServoParamsError(f"{path}: servo parameters are for robot {doc.get('robot')!r}, not {spec.name!r}")
    joints = doc.get("joints")
    if not isinstance(joints, dict):
        raise ServoParamsError(f"{path}: 'joints' must be an object of joint name -> parameters")
    out: dict[str, ServoParams] = {}
    for name, values in joints.items():
        if name not in spec.names:
            raise ServoParamsError(f"{path}: unknown joint {name!r} for {spec.name}; joints: {', '.join(spec.names)}")
        if not isinstance(values, dict):
            raise ServoParamsError(f"{path}: joints.{name} must be an object with {', '.join(FIELDS)}")
        _check_joint(path, name, values)
        out[name] = ServoParams(**{k: float(values[k]) for k in FIELDS})
    return out


def _check_joint(path: Path, name: str, values: Mapping) -> None:
    check_fields(values, FIELDS, f"{path}: joints.{name}", ServoParamsError,
                 unknown="{where}: unknown field {field!r}; fields: {fields}")
    for k in FIELDS:
        v = values[k]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be a number, got {v!r}")
        if not math.isfinite(v):
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be finite, got {v}")
        if v < 0 or (k in _POSITIVE and v == 0):
            need = "positive" if k in _POSITIVE else "non-negative"
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be {need}, got {v}")
