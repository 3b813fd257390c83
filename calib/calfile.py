"""Calibration files: what makes one physical robot match its model, stored per robot id.

A file (JSON, ``schema`` 1) holds the robot type and id, a UTC timestamp and, per joint, what
`felis calibrate` measured and wrote into the servo::

    {"schema": 1, "robot": "cat", "robot_id": "tabby", "created": "2026-11-22T10:00:00Z",
     "joints": {"spine_pitch": {"id": 1, "model": "XL330-M288-T", "firmware": 52,
                                "offset": -37, "direction": 1, "range": [1365, 2731]}, …},
     "imu": {"rotation": [w, x, y, z], "gyro_bias": [x, y, z], …} | null}

``offset`` is the servo's Homing Offset (ticks, |offset| ≤ 1024 in position mode): with it, Present
Position = raw encoder + offset, so at the reference pose (every joint at its MJCF zero) each servo
reads its description zero tick ``2048 + zero/(2π/4096)``. ``direction`` is the description's (the
sign stays on the host; Drive Mode's reverse bit is kept clear). ``range`` is the swept travel in
Present Position ticks, written to Min/Max Position Limit, so the servo itself refuses goals past it.

Files live in ``$XDG_CONFIG_HOME/felis/calibration/<robot>/<robot_id>.json`` (``~/.config`` when
unset) unless a path is given. `save` is atomic: the new text goes to a temporary file in the same
folder, is flushed to disk, the current file is copied to ``<name>.json.bak``, then the temporary file
is renamed over the current one. A process killed at any point leaves either the old or the new file
whole, and never loses the previous version.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from felis.errors import CalibrationError
from felis.files import check_readable, read_text, write_atomic
from felis.servos import RAD_PER_TICK, TICKS_PER_REV
from felis.spec import JointSpec, RobotSpec

SCHEMA = 1
CENTRE = 2048
HOMING_LIMIT = 1024  # |Homing Offset| in position mode (ticks)
MIN_RANGE_TICKS = 23  # ≈ 2°: a narrower swept range means the joint was not moved
REACH_MARGIN = math.radians(10.0)  # a range end may pass the description limit by this much (horn angle)
_ROBOT_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_robot_id(robot_id: str) -> str:
    """A robot id names a file: letters, digits, ``_ . -``, starting with a letter or digit, ≤ 64 long."""
    if not isinstance(robot_id, str) or not _ROBOT_ID.fullmatch(robot_id) or ".." in robot_id:
        raise CalibrationError(f"robot id {robot_id!r} cannot name a calibration file: use letters, digits, '_', "
                               "'.', '-' (no '/', no '..', no spaces), starting with a letter or digit")
    return robot_id


def config_dir() -> Path:
    """``$XDG_CONFIG_HOME/felis/calibration`` (``~/.config/felis/calibration`` when unset)."""
    base = os.environ.get("XDG_CONFIG_HOME") or ""
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".config"
    return root / "felis" / "calibration"


def calibration_path(robot: str, robot_id: str, directory: str | Path | None = None) -> Path:
    """Where the calibration of ``robot`` number ``robot_id`` lives."""
    check_robot_id(robot_id)
    return (Path(directory) if directory is not None else config_dir() / robot) / f"{robot_id}.json"


def backup_path(path: Path) -> Path:
    return path.with_name(path.name + ".bak")


# ----------------------------------------------------------------------------- tick geometry
def zero_tick(j: JointSpec) -> int:
    """Present Position (after Homing Offset) of joint ``j`` at q = 0: ``2048 + zero/(2π/4096)``."""
    return CENTRE + round(j.zero / RAD_PER_TICK)


def horn_of_tick(tick: float) -> float:
    return (tick - CENTRE) * RAD_PER_TICK


def q_of_tick(j: JointSpec, tick: float) -> float:
    """Joint position (rad or m) of a calibrated servo reading ``tick``: ``q = d·(a − zero)·m``."""
    return j.direction * (horn_of_tick(tick) - j.zero) * j.m_per_rad


def tick_of_q(j: JointSpec, q: float) -> int:
    return CENTRE + round((j.direction * q / j.m_per_rad + j.zero) / RAD_PER_TICK)


def description_ticks(j: JointSpec) -> tuple[int, int]:
    """The description's joint limits as position-limit ticks (clipped to one turn)."""
    a, b = tick_of_q(j, j.lower), tick_of_q(j, j.upper)
    return max(0, min(a, b)), min(TICKS_PER_REV - 1, max(a, b))


def check_offset(j: JointSpec, offset: int) -> None:
    """A Homing Offset the servo can hold in position mode (|offset| ≤ 1024 ticks = 90°)."""
    if abs(offset) > HOMING_LIMIT:
        raise CalibrationError(
            f"joint {j.name}: the horn sits {offset * 360 / TICKS_PER_REV:+.1f}° from its reference; the servo's "
            f"Homing Offset holds at most ±90° ({offset:+d} ticks needed, limit ±{HOMING_LIMIT}); remount the horn "
            "on the spline closest to its mark and calibrate again")


def check_range(j: JointSpec, lo: int, hi: int) -> None:
    """A swept or stored range the servo can hold and the joint can reach (one line on failure).

    Rejects: a range that crosses the 0/4095 seam (ends outside one turn), a zero-width range (narrower
    than 2°: the joint was not swept), a range that does not contain the reference pose, and a range
    whose ends lie more than 10° (horn angle) past the description's joint limits.
    """
    if not (isinstance(lo, int) and isinstance(hi, int)):
        raise CalibrationError(f"joint {j.name}: range must be two integer ticks, got {lo!r}, {hi!r}")
    if lo < 0 or hi > TICKS_PER_REV - 1:
        raise CalibrationError(f"joint {j.name}: range {lo}…{hi} crosses the 0/4095 seam; position mode cannot "
                               "hold it: remount the horn so the travel stays inside one turn, then calibrate again")
    if hi - lo < MIN_RANGE_TICKS:
        raise CalibrationError(f"joint {j.name}: range {lo}…{hi} is {(hi - lo) * 360 / TICKS_PER_REV:.1f}° wide: "
                               "the joint was not swept; move it through its whole travel")
    z = zero_tick(j)
    if not lo <= z <= hi:
        raise CalibrationError(f"joint {j.name}: range {lo}…{hi} does not contain the reference pose (tick {z}); "
                               "the joint cannot reach its zero: calibrate the reference pose again")
    dlo, dhi = (horn_of_tick(t) for t in description_ticks(j))
    a, b = horn_of_tick(lo), horn_of_tick(hi)
    if a < dlo - REACH_MARGIN or b > dhi + REACH_MARGIN:
        ql, qh = sorted((q_of_tick(j, lo), q_of_tick(j, hi)))
        unit, k = ("m", 1.0) if j.kind == "prismatic" else ("°", 180 / math.pi)
        raise CalibrationError(
            f"joint {j.name}: range {ql * k:+.1f}…{qh * k:+.1f}{unit} goes past what the joint can reach "
            f"({j.lower * k:+.1f}…{j.upper * k:+.1f}{unit} in {j.name}'s description): a slipped horn or a wrong "
            "description; fix it and sweep again")


# ----------------------------------------------------------------------------- the file
@dataclass(frozen=True)
class JointCalibration:
    """One joint's calibration (ticks are Present Position ticks after the Homing Offset)."""

    id: int
    model: str
    firmware: int
    offset: int  # Homing Offset, ticks
    direction: int  # ±1, from the description
    range: tuple[int, int]  # Min/Max Position Limit, ticks


@dataclass(frozen=True)
class CalibrationFile:
    """A robot's calibration: see the module doc for the format."""

    robot: str
    robot_id: str
    joints: dict[str, JointCalibration]
    created: str = field(default_factory=lambda: now_iso())
    imu: dict | None = None
    schema: int = SCHEMA

    # -------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict:
        joints = {}
        for name, jc in self.joints.items():
            d = asdict(jc)
            d["range"] = list(jc.range)
            joints[name] = d
        return {"schema": self.schema, "robot": self.robot, "robot_id": self.robot_id, "created": self.created,
                "joints": joints, "imu": self.imu}

    @staticmethod
    def from_dict(data: object, source: str = "calibration") -> CalibrationFile:
        """Parse and check the structure (not the robot: see `check`); errors name the key."""
        if not isinstance(data, dict):
            raise CalibrationError(f"{source}: not a calibration file (the top level must be a JSON object)")

        def need(obj: dict, key: str, kind, where: str):
            if key not in obj:
                raise CalibrationError(f"{source}: {where}{key}: missing (the file is partial or corrupt)")
            v = obj[key]
            if kind is int and (isinstance(v, bool) or not isinstance(v, int)):
                raise CalibrationError(f"{source}: {where}{key}: must be an integer, got {v!r}")
            if kind is not int and not isinstance(v, kind):
                raise CalibrationError(f"{source}: {where}{key}: must be {kind.__name__}, got {v!r}")
            return v

        schema = need(data, "schema", int, "")
        if schema != SCHEMA:
            raise CalibrationError(f"{source}: schema {schema} is not supported (this felis reads schema {SCHEMA})")
        robot = need(data, "robot", str, "")
        robot_id = need(data, "robot_id", str, "")
        try:
            check_robot_id(robot_id)
        except CalibrationError as e:
            raise CalibrationError(f"{source}: robot_id: {e}") from None
        created = need(data, "created", str, "")
        raw_joints = need(data, "joints", dict, "")
        if not raw_joints:
            raise CalibrationError(f"{source}: joints: empty (the file is partial)")
        joints = {}
        for name, jd in raw_joints.items():
            where = f"joints.{name}."
            if not isinstance(jd, dict):
                raise CalibrationError(f"{source}: joints.{name}: must be an object")
            rng = need(jd, "range", list, where)
            if len(rng) != 2 or any(isinstance(v, bool) or not isinstance(v, int) for v in rng):
                raise CalibrationError(f"{source}: {where}range: must be [min, max] integer ticks, got {rng!r}")
            direction = need(jd, "direction", int, where)
            if direction not in (1, -1):
                raise CalibrationError(f"{source}: {where}direction: must be 1 or -1, got {direction}")
            joints[name] = JointCalibration(id=need(jd, "id", int, where), model=need(jd, "model", str, where),
                                            firmware=need(jd, "firmware", int, where),
                                            offset=need(jd, "offset", int, where), direction=direction,
                                            range=(rng[0], rng[1]))
        imu = data.get("imu")
        if imu is not None and not isinstance(imu, dict):
            raise CalibrationError(f"{source}: imu: must be an object or null")
        if imu is not None:
            from felis.calib.imu import ImuMounting

            try:
                ImuMounting.from_dict(imu)
            except CalibrationError as e:
                raise CalibrationError(f"{source}: imu: {e}") from None
        return CalibrationFile(robot=robot, robot_id=robot_id, joints=joints, created=created, imu=imu,
                               schema=schema)

    # -------------------------------------------------------------- checks against a description
    def check(self, spec: RobotSpec, source: str = "calibration", *, complete: bool = True) -> None:
        """The file fits ``spec``: same robot, known joints (all of them when ``complete``), the
        description's servo IDs, models and directions, offsets and ranges the servo can hold."""
        if self.robot != spec.name:
            raise CalibrationError(f"{source}: calibrates a {self.robot!r}, not a {spec.name!r}")
        unknown = [n for n in self.joints if n not in spec.names]
        if unknown:
            raise CalibrationError(f"{source}: joint {unknown[0]!r} is not in the {spec.name} description "
                                   f"(joints: {', '.join(spec.names)})")
        missing = [n for n in spec.names if n not in self.joints]
        if complete and missing:
            raise CalibrationError(f"{source}: partial: no calibration for {', '.join(missing)}; run "
                                   f"`felis calibrate --robot {spec.name} --id {self.robot_id} --joints "
                                   f"{','.join(missing)}`")
        for j in spec.joints:
            jc = self.joints.get(j.name)
            if jc is None:
                continue
            try:
                if jc.id != j.servo_id:
                    raise CalibrationError(f"joint {j.name}: servo ID {jc.id}, the description says {j.servo_id}")
                if jc.model != j.servo:
                    raise CalibrationError(f"joint {j.name}: servo {jc.model}, the description says {j.servo}")
                if jc.direction != j.direction:
                    raise CalibrationError(f"joint {j.name}: direction {jc.direction:+d}, the description says "
                                           f"{j.direction:+d}: calibrate this joint again")
                check_offset(j, jc.offset)
                check_range(j, *jc.range)
            except CalibrationError as e:
                raise CalibrationError(f"{source}: {e}") from None

    def for_robot(self, spec: RobotSpec):
        """The host-side `felis.drivers.dynamixel.robot.Calibration` for ``spec`` (checks the file first)."""
        from felis.drivers.dynamixel.robot import Calibration

        self.check(spec)
        n = spec.n
        rot = bias = None
        if self.imu is not None:
            from felis.calib.imu import ImuMounting

            m = ImuMounting.from_dict(self.imu)
            rot, bias = np.asarray(m.rotation, float), np.asarray(m.gyro_bias, float)
        js = [self.joints[name] for name in spec.names]
        return Calibration(direction=np.ones(n), offset=np.zeros(n), imu_rotation=rot, gyro_bias=bias,
                           homing=np.array([jc.offset for jc in js], dtype=np.int64),
                           tick_range=(np.array([jc.range[0] for jc in js]), np.array([jc.range[1] for jc in js])))

    def with_joints(self, joints: dict[str, JointCalibration], spec: RobotSpec | None = None) -> CalibrationFile:
        """A copy with ``joints`` replaced (in description order when ``spec`` is given), stamped now."""
        merged = {**self.joints, **joints}
        if spec is not None:
            merged = {n: merged[n] for n in spec.names if n in merged}
        return replace(self, joints=merged, created=now_iso())


def now_iso() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


# ----------------------------------------------------------------------------- load / save
def load(path: str | Path, spec: RobotSpec | None = None, *, complete: bool = True) -> CalibrationFile:
    """Read and check a calibration file; every problem is one `CalibrationError` line."""
    path = Path(path)
    data = read_json(path, "calibration file")
    try:
        cal = CalibrationFile.from_dict(data, str(path))
        if spec is not None:
            cal.check(spec, str(path), complete=complete)
    except CalibrationError as e:
        raise CalibrationError(f"{e}{backup_hint(path)}") from None
    return cal


def read_json(path: Path, what: str):
    """The JSON of a file kept with a backup (a calibration, a pose file); every problem one `CalibrationError`
    line naming the backup where there is one."""
    text = read_text(path, what, CalibrationError, hint=lambda: backup_hint(path),
                     missing=f"no {what} at {{path}}", directory=None,
                     undecodable="{path}: not a text file (corrupt){hint}", unreadable="cannot read {path}: {reason}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        bad = "empty" if not text.strip() else f"not valid JSON at line {e.lineno} column {e.colno}"
        raise CalibrationError(f"{path}: {bad} (corrupt or cut short){backup_hint(path)}") from None


def backup_hint(path: Path) -> str:
    bak = backup_path(path)
    return f"; the previous version is {bak}" if bak.is_file() and bak != path else ""


def save(cal: CalibrationFile, path: str | Path) -> Path:
    """Write ``cal`` atomically to ``path``, keeping the current file as ``<path>.bak`` (module doc)."""
    path = Path(path)
    check_robot_id(cal.robot_id)
    text = json.dumps(cal.to_dict(), indent=2) + "\n"
    return write_atomic(path, text, "calibration file", CalibrationError, backup=backup_path(path))


def copy_out(src: Path, dst: str | Path) -> Path:
    """Export: copy a checked calibration file to ``dst`` (atomic, like `save`)."""
    check_readable(src, "calibration file", CalibrationError)
    return write_atomic(dst, Path(src).read_bytes(), "calibration file", CalibrationError)


def stale_temps(folder: Path) -> list[Path]:
    """Temporary files a killed write left behind (harmless; `felis calibration show` lists them)."""
    return sorted(folder.glob(".*.json.*.tmp")) if folder.is_dir() else []


__all__ = ["SCHEMA", "CalibrationFile", "JointCalibration", "backup_hint", "backup_path", "calibration_path",
           "check_offset", "check_range", "check_robot_id", "config_dir", "copy_out", "description_ticks", "load",
           "q_of_tick", "read_json", "save", "tick_of_q", "zero_tick"]
