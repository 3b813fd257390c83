"""Pose files: named joint poses of one physical robot, taught by hand (`felis pose capture`) and played back
(`felis pose play`).

A pose file sits beside the robot's calibration, ``$XDG_CONFIG_HOME/felis/calibration/<robot>/<robot_id>.poses.json``
(`poses_path`), because its angles mean something only through that calibration: they are the calibrated joint
positions `felis.drivers.dynamixel.robot.DynamixelRobot` read, in the description's units (rad; m for a prismatic
joint), the same numbers the MJCF model and the description's ``[poses.NAME]`` use. JSON, ``schema`` 1::

    {"schema": 1, "robot": "arm", "robot_id": "bench-1",
     "poses": {"wave": {"created": "2026-11-26T07:00:00Z", "joints": {"joint1": 0.1, "joint2": -0.4, …}}, …}}

Every pose gives every joint of the description (as a description pose does), each a finite number within the
joint's limits widened by one encoder tick (``2π/4096`` rad of horn, ``·m_per_rad`` for a prismatic joint: a joint
held at its limit may read half a tick past it). Pose names are ``[A-Za-z0-9][A-Za-z0-9_.-]{0,63}``; ``hold`` is
taken (the pose controller's "where it is").

The description's named poses stay the defaults (`known_poses`): a file pose of the same name overrides it for this
robot, which `felis pose capture` does only when told (``--force``). `save` is atomic and keeps the previous file
as ``<name>.bak``, as `felis.calib.calfile.save` does.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from felis.calib.calfile import backup_hint, backup_path, check_robot_id, config_dir, now_iso, read_json
from felis.errors import CalibrationError, ParameterError
from felis.files import write_atomic
from felis.servos import RAD_PER_TICK
from felis.spec import RobotSpec

SCHEMA = 1
HOLD = "hold"  # the pose controller's "the present pose": not a name a pose can take
FILE, DESCRIPTION = "file", "description"  # where a pose comes from
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_pose_name(name: str) -> str:
    """A pose name: letters, digits, ``_ . -``, starting with a letter or digit, ≤ 64 long; not ``hold``."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ParameterError(f"pose name {name!r}: use letters, digits, '_', '.', '-' (no spaces), starting with a "
                             "letter or digit, at most 64 characters")
    if name == HOLD:
        raise ParameterError("pose name 'hold' is taken (it means the present pose); choose another")
    return name


def poses_path(robot: str, robot_id: str) -> Path:
    """Where the poses of ``robot`` number ``robot_id`` live: beside its calibration file."""
    check_robot_id(robot_id)
    return config_dir() / robot / f"{robot_id}.poses.json"


def tick_in_joint_units(spec: RobotSpec) -> np.ndarray:
    """One encoder tick of each joint in joint units: ``2π/4096 · m_per_rad`` (rad, or m for a prismatic joint)."""
    return np.array([RAD_PER_TICK * j.m_per_rad for j in spec.joints])


@dataclass(frozen=True)
class Pose:
    """A named pose: every joint's position (rad/m) in description order; ``created`` (UTC) for a file pose."""

    name: str
    q: np.ndarray
    source: str  # FILE or DESCRIPTION
    created: str | None = None

    def joints(self, spec: RobotSpec) -> dict[str, float]:
        return {n: float(v) for n, v in zip(spec.names, self.q, strict=True)}


@dataclass(frozen=True)
class PoseFile:
    """One robot's taught poses (module doc); ``poses`` maps a name to (created, {joint: position})."""

    robot: str
    robot_id: str
    poses: dict[str, tuple[str, dict[str, float]]] = field(default_factory=dict)
    schema: int = SCHEMA

    def to_dict(self) -> dict:
        return {"schema": self.schema, "robot": self.robot, "robot_id": self.robot_id,
                "poses": {n: {"created": c, "joints": dict(j)} for n, (c, j) in self.poses.items()}}

    @staticmethod
    def from_dict(data: object, source: str = "pose file") -> PoseFile:
        """Parse and check the structure (not the robot: see `check`); errors name the key."""
        if not isinstance(data, dict):
            raise CalibrationError(f"{source}: not a pose file (the top level must be a JSON object)")
        for key, kind in (("schema", int), ("robot", str), ("robot_id", str), ("poses", dict)):
            if key not in data:
                raise CalibrationError(f"{source}: {key}: missing (the file is partial or corrupt)")
            v = data[key]
            if not isinstance(v, kind) or isinstance(v, bool):
                raise CalibrationError(f"{source}: {key}: must be {kind.__name__}, got {v!r}")
        if data["schema"] != SCHEMA:
            raise CalibrationError(f"{source}: schema {data['schema']} is not supported (this felis reads schema "
                                   f"{SCHEMA})")
        poses = {}
        for name, p in data["poses"].items():
            where = f"{source}: poses.{name}"
            try:
                check_pose_name(name)
            except ParameterError as e:
                raise CalibrationError(f"{where}: {e}") from None
            if not isinstance(p, dict) or not isinstance(p.get("joints"), dict):
                raise CalibrationError(f"{where}: must be an object with \"joints\": {{joint: position}}")
            created = p.get("created", "")
            if not isinstance(created, str):
                raise CalibrationError(f"{where}.created: must be a string, got {created!r}")
            joints = {}
            for joint, v in p["joints"].items():
                if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                    raise CalibrationError(f"{where}.joints.{joint}: must be a finite number, got {v!r}")
                joints[joint] = float(v)
            poses[name] = (created, joints)
        return PoseFile(robot=data["robot"], robot_id=data["robot_id"], poses=poses, schema=data["schema"])

    def check(self, spec: RobotSpec, source: str = "pose file", robot_id: str | None = None) -> None:
        """The file fits ``spec`` (and ``robot_id`` when given): same robot, every pose giving every joint of
        the description and nothing else, within the joints' limits (± one tick)."""
        if self.robot != spec.name:
            raise CalibrationError(f"{source}: holds poses of a {self.robot!r}, not of a {spec.name!r}")
        if robot_id is not None and self.robot_id != robot_id:
            raise CalibrationError(f"{source}: holds the poses of {self.robot} {self.robot_id!r}, not of "
                                   f"{robot_id!r} (a copied file? poses belong to the robot whose calibration "
                                   "they were read through)")
        tick = tick_in_joint_units(spec)
        for name, (_, joints) in self.poses.items():
            where = f"{source}: pose {name!r}"
            unknown = [j for j in joints if j not in spec.names]
            if unknown:
                raise CalibrationError(f"{where}: joint {unknown[0]!r} is not in the {spec.name} description "
                                       f"(joints: {', '.join(spec.names)})")
            missing = [j for j in spec.names if j not in joints]
            if missing:
                raise CalibrationError(f"{where}: no position for {', '.join(missing)} (a pose gives every joint)")
            for k, j in enumerate(spec.joints):
                v = joints[j.name]
                if not j.lower - tick[k] <= v <= j.upper + tick[k]:
                    raise CalibrationError(f"{where}: {j.name} = {v:.4f} is outside its limits "
                                           f"{j.lower:.4f}…{j.upper:.4f}")

    def pose(self, spec: RobotSpec, name: str) -> Pose:
        created, joints = self.poses[name]
        return Pose(name, np.array([joints[n] for n in spec.names]), FILE, created)

    def with_pose(self, spec: RobotSpec, name: str, q: np.ndarray, created: str | None = None) -> PoseFile:
        """A copy with pose ``name`` set to ``q`` (description order), stamped now unless ``created`` is given."""
        joints = {n: float(v) for n, v in zip(spec.names, np.asarray(q, float), strict=True)}
        return replace(self, poses={**self.poses, name: (created or now_iso(), joints)})

    def without(self, name: str) -> PoseFile:
        return replace(self, poses={n: p for n, p in self.poses.items() if n != name})


# ----------------------------------------------------------------------------- load / save
def load(path: str | Path, spec: RobotSpec | None = None, *, robot_id: str | None = None,
         missing_ok: bool = False) -> PoseFile | None:
    """Read and check a pose file; every problem is one `CalibrationError` line (naming the backup if there
    is one). A missing file is None with ``missing_ok`` (a robot that has no taught poses yet)."""
    path = Path(path)
    if missing_ok and not path.exists():
        return None
    data = read_json(path, "pose file")
    try:
        pf = PoseFile.from_dict(data, str(path))
        if spec is not None:
            pf.check(spec, str(path), robot_id)
    except CalibrationError as e:
        raise CalibrationError(f"{e}{backup_hint(path)}") from None
    return pf


def save(pf: PoseFile, path: str | Path) -> Path:
    """Write ``pf`` atomically to ``path``, keeping the current file as ``<path>.bak`` (module doc)."""
    check_robot_id(pf.robot_id)
    text = json.dumps(pf.to_dict(), indent=2) + "\n"
    return write_atomic(Path(path), text, "pose file", CalibrationError, backup=backup_path(Path(path)))


# ----------------------------------------------------------------------------- file poses, then the description's
def known_poses(spec: RobotSpec, pf: PoseFile | None) -> dict[str, Pose]:
    """Every pose ``spec``'s robot knows: the file's (in file order), then the description's not overridden."""
    out = {} if pf is None else {n: pf.pose(spec, n) for n in pf.poses}
    for n, q in spec.poses.items():
        out.setdefault(n, Pose(n, np.array(q, float), DESCRIPTION))
    return out


def resolve(spec: RobotSpec, pf: PoseFile | None, names: list[str]) -> list[Pose]:
    """The poses called ``names``, file first; an unknown name is one line listing the known ones."""
    known = known_poses(spec, pf)
    for n in names:
        if n not in known:
            raise ParameterError(f"no pose {n!r} for the {spec.name}{_whose(pf)}; known: {describe(known)}")
    return [known[n] for n in names]


def describe(known: dict[str, Pose]) -> str:
    """``wave, reach (taught); zero, stand, sit (description)``."""
    parts = []
    for src, label in ((FILE, "taught"), (DESCRIPTION, "description")):
        names = [n for n, p in known.items() if p.source == src]
        if names:
            parts.append(f"{', '.join(names)} ({label})")
    return "; ".join(parts) or "none"


def _whose(pf: PoseFile | None) -> str:
    return "" if pf is None else f" {pf.robot_id!r}"


__all__ = ["DESCRIPTION", "FILE", "HOLD", "SCHEMA", "Pose", "PoseFile", "check_pose_name", "describe", "known_poses",
           "load", "poses_path", "resolve", "save", "tick_in_joint_units"]
