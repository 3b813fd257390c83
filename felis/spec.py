"""Robot descriptions: `JointSpec`, `RobotSpec` and their loader.

A description is a TOML file (``felis/robots/<name>.toml``) that fixes, for one robot, the joint
order every array in the HAL follows, and for each joint its servo ID and model, its limits
(radians; metres for a prismatic joint), its calibration (direction and zero) and its group.
It also names the sensors, the link masses the balance monitor needs, and named poses.

Joint-to-servo mapping, used by the Dynamixel backend and by the limit check below::

    servo_angle = direction * q / m_per_rad + zero        (rad around the centre tick 2048)

``m_per_rad`` is 1 for revolute joints (q in rad) and the transmission (metres of travel per
radian of horn) for prismatic ones. In position mode a servo covers one turn, so every joint's
range must map into [-π, π]; a description that asks for more is rejected.

Loading validates everything and raises :class:`DescriptionError` with ``<file>: <key>: <problem>``
on the first fault: unknown keys, missing joints, bad types, limits outside the servo's span or
speed, duplicate servo IDs, poses or groups naming unknown joints.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import DescriptionError, ParameterError, UnknownRobotError
from felis.files import check_readable
from felis.servos import SERVOS, servo_model

SCHEMA = 1
MAX_SERVO_ID = 252


@dataclass(frozen=True)
class JointSpec:
    """One actuated joint and the servo that drives it."""

    name: str
    servo_id: int
    servo: str  # model name, a key of felis.servos.SERVOS
    lower: float  # rad (m for prismatic)
    upper: float
    group: str
    kind: str = "revolute"  # or "prismatic"
    direction: int = 1  # +1 or -1: sign of the servo angle relative to q
    zero: float = 0.0  # servo angle (rad, around tick 2048) at q = 0
    m_per_rad: float = 1.0  # transmission; 1 for revolute joints
    max_velocity: float = 0.0  # rad/s (m/s); filled from the servo's no-load speed if not given
    # The servo's firmware controller (`felis.drivers.virtual.horn`): Operating Mode 3 (position), 4 (extended
    # position) or 5 (current-based position); Position P/I/D Gain and Feedforward 1st/2nd Gain (control-table
    # units; None = the model's factory value); Goal Current (A) capping the torque in mode 5 (None: Current Limit).
    operating_mode: int = 3
    pid: tuple[int | None, int | None, int | None] = (None, None, None)
    feedforward: tuple[int | None, int | None] = (None, None)
    goal_current: float | None = None


@dataclass(frozen=True)
class SensorSpec:
    """Which sensors the robot has; names refer to MJCF sites/bodies."""

    imu: str | None = None  # site carrying the IMU
    contacts: tuple[str, ...] = ()  # feet with contact sensors, in State.contacts order
    height: str | None = None  # site whose height above ground is State.height


@dataclass(frozen=True)
class RobotSpec:
    """A loaded robot description; joint order is the order of every HAL array."""

    name: str
    source: str
    model: str  # MJCF file name in felis/sim/models
    rate_hz: float
    joints: tuple[JointSpec, ...]
    groups: dict[str, tuple[str, ...]]
    sensors: SensorSpec
    links: dict[str, float] = field(default_factory=dict)  # body name -> mass (kg)
    poses: dict[str, np.ndarray] = field(default_factory=dict)  # name -> q (rad/m)
    description: str = ""

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.upper for j in self.joints])

    @property
    def max_velocity(self) -> np.ndarray:
        return np.array([j.max_velocity for j in self.joints])

    def index(self, joint: str) -> int:
        try:
            return self.names.index(joint)
        except ValueError:
            raise KeyError(f"robot {self.name!r} has no joint {joint!r}; joints: {', '.join(self.names)}") from None

    def indices(self, group_or_joints: str | list[str] | tuple[str, ...]) -> np.ndarray:
        """Indices of a group (by name) or of a list of joint names."""
        if isinstance(group_or_joints, str):
            if group_or_joints not in self.groups:
                raise KeyError(f"robot {self.name!r} has no group {group_or_joints!r}; "
                               f"groups: {', '.join(self.groups)}")
            group_or_joints = self.groups[group_or_joints]
        return np.array([self.index(j) for j in group_or_joints], dtype=int)

    def pose(self, name: str) -> np.ndarray:
        if name not in self.poses:
            raise KeyError(f"robot {self.name!r} has no pose {name!r}; poses: {', '.join(self.poses)}")
        return self.poses[name].copy()


# ---------------------------------------------------------------------------------------------
# loading

ROBOTS_DIR = resources.files("felis") / "robots"

_TOP_KEYS = {"schema", "name", "description", "model", "rate_hz", "joints", "joint", "sensors",
             "links", "poses"}
_JOINT_KEYS = {"id", "servo", "range", "range_deg", "group", "kind", "direction", "zero",
               "m_per_rad", "max_velocity", "operating_mode", "pid", "feedforward", "goal_current"}
OPERATING_MODES = {3: "position", 4: "extended position", 5: "current-based position"}  # what a joint may run
EXTENDED_TURNS = 256  # extended position mode: ±256 turns
GAIN_MAX = 16383
_SENSOR_KEYS = {"imu", "contacts", "height"}


def available_robots() -> list[str]:
    """Names of the descriptions shipped in ``felis/robots``."""
    return sorted(p.name[:-5] for p in ROBOTS_DIR.iterdir() if p.name.endswith(".toml"))


def load_spec(robot: str | Path) -> RobotSpec:
    """Load a description by robot name (``"cat"``) or by path to a TOML file."""
    text_path = str(robot)
    if text_path.endswith(".toml") or "/" in text_path or isinstance(robot, Path):
        path = Path(robot)
        if not path.is_file():
            if path.exists() and not path.is_dir():
                check_readable(path, "robot description", ParameterError)
            raise DescriptionError(str(path), "file", "no such description file")
        check_readable(path, "robot description", ParameterError)
        return parse_spec(path.read_bytes().decode("utf-8", errors="replace"), str(path))
    resource = ROBOTS_DIR / f"{robot}.toml"
    if not resource.is_file():
        raise UnknownRobotError(f"unknown robot {robot!r}; known robots: {', '.join(available_robots())}")
    return parse_spec(resource.read_text(encoding="utf-8"), f"felis/robots/{robot}.toml")


def parse_spec(text: str, source: str = "<string>") -> RobotSpec:
    """Parse and validate description text; ``source`` names it in error messages."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise DescriptionError(source, "toml", f"not valid TOML ({e})") from None
    return _Validator(source).spec(doc)


class _Validator:
    def __init__(self, source: str):
        self.source = source

    def fail(self, key: str, problem: str) -> DescriptionError:
        return DescriptionError(self.source, key, problem)

    def keys(self, table: dict, allowed: set[str], where: str) -> None:
        unknown = sorted(set(table) - allowed)
        if unknown:
            prefix = f"{where}." if where else ""
            raise self.fail(prefix + unknown[0], f"unknown key; allowed: {', '.join(sorted(allowed))}")

    def get(self, table: dict, key: str, kind: type | tuple, where: str, default: Any = ...) -> Any:
        full = f"{where}.{key}" if where else key
        if key not in table:
            if default is ...:
                raise self.fail(full, "missing")
            return default
        value = table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(value, bool) and kind is not bool or not isinstance(value, kind):
            names = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            raise self.fail(full, f"expected {names}, got {type(value).__name__} {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise self.fail(full, f"must be finite, got {value}")
        return value

    def number_pair(self, table: dict, key: str, where: str) -> tuple[float, float]:
        full = f"{where}.{key}"
        value = table[key]
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)):
            raise self.fail(full, f"expected [lower, upper], got {value!r}")
        lo, hi = float(value[0]), float(value[1])
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise self.fail(full, "limits must be finite")
        if not lo < hi:
            raise self.fail(full, f"lower limit {value[0]} must be below upper limit {value[1]}")
        return lo, hi

    def spec(self, doc: dict) -> RobotSpec:
        self.keys(doc, _TOP_KEYS, "")
        schema = self.get(doc, "schema", int, "")
        if schema != SCHEMA:
            raise self.fail("schema", f"version {schema} not supported (this felis reads {SCHEMA})")
        name = self.get(doc, "name", str, "")
        model = self.get(doc, "model", str, "")
        rate = self.get(doc, "rate_hz", float, "", 100.0)
        if not 1.0 <= rate <= 2000.0:
            raise self.fail("rate_hz", f"{rate} Hz outside 1…2000")
        order = self.get(doc, "joints", list, "")
        if not order or not all(isinstance(j, str) for j in order):
            raise self.fail("joints", "expected a non-empty list of joint names")
        dup = [j for j in order if order.count(j) > 1]
        if dup:
            raise self.fail("joints", f"joint {dup[0]!r} listed twice")
        tables = self.get(doc, "joint", dict, "")
        for jname in order:
            if jname not in tables:
                raise self.fail(f"joint.{jname}", "missing: listed in `joints` but has no [joint.NAME] table")
        for jname in tables:
            if jname not in order:
                raise self.fail(f"joint.{jname}", "unknown joint: not listed in `joints`")
        joints = tuple(self.joint(jname, tables[jname]) for jname in order)
        seen: dict[int, str] = {}
        for j in joints:
            if j.servo_id in seen:
                raise self.fail(f"joint.{j.name}.id", f"servo ID {j.servo_id} already used by {seen[j.servo_id]}")
            seen[j.servo_id] = j.name
        groups: dict[str, list[str]] = {}
        for j in joints:
            groups.setdefault(j.group, []).append(j.name)
        sensors = self.sensors(doc.get("sensors", {}))
        links = self.links(doc.get("links", {}))
        poses = self.poses(doc.get("poses", {}), joints)
        return RobotSpec(
            name=name, source=self.source, model=model, rate_hz=rate, joints=joints,
            groups={g: tuple(v) for g, v in groups.items()}, sensors=sensors, links=links, poses=poses,
            description=self.get(doc, "description", str, "", ""),
        )

    def joint(self, jname: str, t: Any) -> JointSpec:
        where = f"joint.{jname}"
        if not isinstance(t, dict):
            raise self.fail(where, "expected a table")
        self.keys(t, _JOINT_KEYS, where)
        sid = self.get(t, "id", int, where)
        if not 0 <= sid <= MAX_SERVO_ID:
            raise self.fail(f"{where}.id", f"servo ID {sid} outside 0…{MAX_SERVO_ID}")
        servo = self.get(t, "servo", str, where)
        if servo not in SERVOS:
            raise self.fail(f"{where}.servo", f"unknown servo model {servo!r}; known: {', '.join(SERVOS)}")
        kind = self.get(t, "kind", str, where, "revolute")
        if kind not in ("revolute", "prismatic"):
            raise self.fail(f"{where}.kind", f"expected 'revolute' or 'prismatic', got {kind!r}")
        has_rad, has_deg = "range" in t, "range_deg" in t
        if has_rad == has_deg:
            raise self.fail(f"{where}.range", "give exactly one of `range` (rad, m) or `range_deg`")
        if has_deg:
            if kind == "prismatic":
                raise self.fail(f"{where}.range_deg", "a prismatic joint's range is in metres: use `range`")
            lo, hi = (math.radians(v) for v in self.number_pair(t, "range_deg", where))
        else:
            lo, hi = self.number_pair(t, "range", where)
        direction = self.get(t, "direction", int, where, 1)
        if direction not in (1, -1):
            raise self.fail(f"{where}.direction", f"must be 1 or -1, got {direction}")
        zero = self.get(t, "zero", float, where, 0.0)
        m_per_rad = self.get(t, "m_per_rad", float, where, 1.0)
        if kind == "revolute" and m_per_rad != 1.0:
            raise self.fail(f"{where}.m_per_rad", "only prismatic joints have a transmission")
        if m_per_rad <= 0:
            raise self.fail(f"{where}.m_per_rad", f"must be positive, got {m_per_rad}")
        model = servo_model(servo)
        mode = self.get(t, "operating_mode", int, where, 3)
        if mode not in OPERATING_MODES:
            raise self.fail(f"{where}.operating_mode", f"{mode} is not a position mode the HAL drives; use "
                            + ", ".join(f"{k} ({v})" for k, v in OPERATING_MODES.items()))
        pid = self.gains(t, "pid", 3, where)
        ff = self.gains(t, "feedforward", 2, where)
        goal_current = self.get(t, "goal_current", float, where, None)
        if goal_current is not None and (mode != 5 or goal_current <= 0):
            raise self.fail(f"{where}.goal_current", "a positive current (A), only in operating_mode 5"
                            if mode == 5 else "applies to operating_mode 5 (current-based position) only")
        s_lo, s_hi = sorted((direction * lo / m_per_rad + zero, direction * hi / m_per_rad + zero))
        span_lo, span_hi = model.position_range
        if mode == 4:
            span_lo, span_hi = -EXTENDED_TURNS * 2 * math.pi, EXTENDED_TURNS * 2 * math.pi
        eps = 1e-9
        if s_lo < span_lo - eps or s_hi > span_hi + eps:
            raise self.fail(
                f"{where}.{'range_deg' if has_deg else 'range'}",
                f"maps to servo angles {s_lo:.3f}…{s_hi:.3f} rad, outside what a {servo} covers in "
                f"operating mode {mode} ({span_lo:.3f}…{span_hi:.3f} rad around its zero)",
            )
        vmax_servo = model.no_load_speed * m_per_rad
        vmax = self.get(t, "max_velocity", float, where, vmax_servo)
        if not 0 < vmax <= vmax_servo + eps:
            raise self.fail(f"{where}.max_velocity",
                            f"{vmax} outside 0…{vmax_servo:.3f} (the {servo}'s no-load speed)")
        group = self.get(t, "group", str, where)
        return JointSpec(name=jname, servo_id=sid, servo=servo, lower=lo, upper=hi, group=group, kind=kind,
                         direction=direction, zero=zero, m_per_rad=m_per_rad, max_velocity=vmax, operating_mode=mode,
                         pid=pid, feedforward=ff, goal_current=goal_current)

    def gains(self, t: dict, key: str, n: int, where: str) -> tuple:
        """``key = [g1, …]``: n control-table gains (0…16383), or absent: (None,)*n (the factory values)."""
        if key not in t:
            return (None,) * n
        value = t[key]
        if (not isinstance(value, list) or len(value) != n
                or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= GAIN_MAX for v in value)):
            raise self.fail(f"{where}.{key}", f"expected {n} integer gains 0…{GAIN_MAX} (control-table units), "
                            f"got {value!r}")
        return tuple(value)

    def sensors(self, t: Any) -> SensorSpec:
        if not isinstance(t, dict):
            raise self.fail("sensors", "expected a table")
        self.keys(t, _SENSOR_KEYS, "sensors")
        imu = self.get(t, "imu", str, "sensors", None)
        height = self.get(t, "height", str, "sensors", None)
        contacts = self.get(t, "contacts", list, "sensors", [])
        if not all(isinstance(c, str) for c in contacts):
            raise self.fail("sensors.contacts", "expected a list of foot body names")
        return SensorSpec(imu=imu, contacts=tuple(contacts), height=height)

    def links(self, t: Any) -> dict[str, float]:
        if not isinstance(t, dict):
            raise self.fail("links", "expected a table of body name = mass (kg)")
        out = {}
        for body in t:
            m = self.get(t, body, float, "links")
            if m <= 0:
                raise self.fail(f"links.{body}", f"mass must be positive, got {m}")
            out[body] = m
        return out

    def poses(self, t: Any, joints: tuple[JointSpec, ...]) -> dict[str, np.ndarray]:
        if not isinstance(t, dict):
            raise self.fail("poses", "expected [poses.NAME] tables")
        names = [j.name for j in joints]
        out = {}
        for pname, table in t.items():
            where = f"poses.{pname}"
            if not isinstance(table, dict):
                raise self.fail(where, "expected a table of joint = position")
            self.keys(table, set(names), where)
            q = np.empty(len(joints))
            for i, j in enumerate(joints):
                if j.name not in table:
                    raise self.fail(f"{where}.{j.name}", "missing: a pose gives every joint")
                v = self.get(table, j.name, float, where)
                if not j.lower <= v <= j.upper:
                    raise self.fail(f"{where}.{j.name}", f"{v} outside the joint's range {j.lower:.4g}…{j.upper:.4g}")
                q[i] = v
            q.setflags(write=False)
            out[pname] = q
        return out
