"""Servo parameter files: per-joint `ServoParams` for the MuJoCo backend, as `felis sysid` writes them.

Format (JSON, SI units in joint coordinates: rad, or m for a prismatic joint)::

    {"schema": 1, "robot": "cat",
     "joints": {"fl_pitch": {"kp": 1.66, "torque_limit": 0.41, "damping": 0.034,
                             "armature": 0.001, "frictionloss": 0.0075,
                             "pid": [800, 100, 100]}, ...},       # optional: Position P/I/D Gain

     "fit": {...}}                      # optional: how the numbers were obtained (free-form)

``pid`` (optional; `felis sysid` writes the gains it fitted) is the Position P, I, D Gain in control-table units
the servo runs: the MuJoCo joint then runs the firmware's controller at those gains (`felis.sim.servo.controller`;
``kp`` is P's stiffness); without it, the description's gains. Joints not listed keep the datasheet model
(`felis.sim.servo.servo_params`). Loading checks
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
FIELDS = tuple(f.name for f in fields(ServoParams) if f.name != "pid")  # required; "pid" is optional
_POSITIVE = ("kp", "torque_limit")


def servo_params_dict(params: Mapping[str, ServoParams]) -> dict[str, dict[str, float]]:
    """``{joint: {field: value}}``, the file's ``joints`` object."""
    out = {}
    for name, p in params.items():
        d = {k: float(v) for k, v in asdict(p).items() if k != "pid"}
        if p.pid is not None:
            d["pid"] = [float(g) for g in p.pid]
        out[name] = d
    return out


def save_servo_params(path: str | os.PathLike, robot: str, params: Mapping[str, ServoParams],
                      fit: Mapping | None = None) -> Path:
    """Write ``params`` for ``robot`` to ``path`` atomically; returns the path.

    ``fit`` (optional, JSON-serialisable) records how the parameters were obtained.
    """
    path = Path(path)
    for name, p in params.items():
        _check_joint(path, name, servo_params_dict({name: p})[name])
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
        pid = values.get("pid")
        out[name] = ServoParams(**{k: float(values[k]) for k in FIELDS},
                                pid=None if pid is None else tuple(float(g) for g in pid))
    return out


def _check_joint(path: Path, name: str, values: Mapping) -> None:
    pid = values.get("pid") if isinstance(values, dict) else None
    if isinstance(values, dict) and "pid" in values:
        values = {k: v for k, v in values.items() if k != "pid"}
        if (not isinstance(pid, list) or len(pid) != 3
                or not all(isinstance(g, int | float) and not isinstance(g, bool) and math.isfinite(g) and g >= 0
                           for g in pid)):
            raise ServoParamsError(f"{path}: joints.{name}.pid must be [P, I, D], three non-negative numbers, "
                                   f"got {pid!r}")
    check_fields(values, FIELDS, f"{path}: joints.{name}", ServoParamsError,
                 unknown="{where}: unknown field {field!r}; fields: {fields}, pid")
    for k in FIELDS:
        v = values[k]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be a number, got {v!r}")
        if not math.isfinite(v):
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be finite, got {v}")
        if v < 0 or (k in _POSITIVE and v == 0):
            need = "positive" if k in _POSITIVE else "non-negative"
            raise ServoParamsError(f"{path}: joints.{name}.{k} must be {need}, got {v}")
