"""What each servo's EEPROM should hold, what it holds, and how to reconcile them.

Two comparisons, one mechanism (`Difference` rows, printed as a table, applied on an explicit choice):

* **Settings** (`check_settings`), run when a robot connects (`felis run --backend dxl`,
  `felis check-eeprom`): Return Delay Time 0 (the factory 500 µs costs 6 ms per 12-servo read),
  Operating Mode (the joint's, from the description: 3 position, 4 extended position, 5 current-based
  position, as `DynamixelRobot` drives it), Drive Mode 0 (direction is applied on the
  host, from the description), Min/Max Position Limit (the calibrated range, else the description's
  limits), Shutdown 52 (overheating, electrical shock, overload: the factory mask the loop's hardware
  error handling expects) and Baud Rate (the robot's rate).
* **Calibration** (`diff_calibration`): the calibration file against the motors: Homing Offset and
  Min/Max Position Limit per joint (plus the servo's model and firmware, reported, not written).
  `apply_calibration` resolves it by an explicit choice: ``prefer="file"`` writes the file's values
  into the motors, ``prefer="motors"`` rewrites the file from the motors (atomically, the old file
  kept as a backup) after checking that they form a valid calibration.

Writes go to EEPROM, so torque goes off on the servos concerned first, and each write is read back.
Baud Rate is written last, after which the bus follows the servos to the new rate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from felis.calib.calfile import (
    CalibrationFile,
    JointCalibration,
    check_offset,
    check_range,
    description_ticks,
    save,
)
from felis.calib.joints import check_servos, write_eeprom
from felis.drivers.dynamixel.bus import DynamixelBus, baud_code
from felis.drivers.dynamixel.controltable import control_table
from felis.errors import CalibrationError, CommError, ParameterError
from felis.spec import RobotSpec

SHUTDOWN_MASK = 0x34  # overheating | electrical shock | overload (factory default)
SETTINGS = ("return_delay_time", "operating_mode", "drive_mode", "min_position_limit", "max_position_limit",
            "shutdown", "baud_rate")
CALIBRATED = ("homing_offset", "min_position_limit", "max_position_limit")


@dataclass(frozen=True)
class Difference:
    """One item where a servo's EEPROM and the expectation disagree."""

    joint: str
    servo_id: int
    item: str
    motor: int
    expected: int  # the description's / calibration file's value

    def as_dict(self) -> dict:
        return asdict(self)


def expected_settings(spec: RobotSpec, baud: int, cal: CalibrationFile | None = None) -> dict[str, dict[str, int]]:
    """{joint: {item: raw value}} the servos should hold (module doc)."""
    out = {}
    for j in spec.joints:
        table = control_table(j.servo)
        if cal is not None and j.name in cal.joints:
            lo, hi = cal.joints[j.name].range
        else:
            lo, hi = description_ticks(j)
        out[j.name] = {"return_delay_time": 0, "operating_mode": j.operating_mode, "drive_mode": 0,
                       "min_position_limit": lo, "max_position_limit": hi, "shutdown": SHUTDOWN_MASK,
                       "baud_rate": baud_code(table, baud)}
    return out


def read_items(bus: DynamixelBus, spec: RobotSpec, items: tuple[str, ...]) -> dict[str, dict[str, int]]:
    """{joint: {item: raw}} read from every servo (one read of the EEPROM area per servo)."""
    out = {}
    for j in spec.joints:
        table = bus.table(j.servo_id)
        its = [table.item(n) for n in items]
        start = min(it.addr for it in its)
        end = max(it.addr + it.size for it in its)
        raw = bus.read_raw(j.servo_id, start, end - start)
        out[j.name] = {it.name: it.decode(raw[it.addr - start: it.addr - start + it.size]) for it in its}
    return out


def _diff(spec: RobotSpec, held: dict, want: dict, items) -> list[Difference]:
    return [Difference(j.name, j.servo_id, item, held[j.name][item], want[j.name][item])
            for j in spec.joints if j.name in want for item in items if held[j.name][item] != want[j.name][item]]


def check_settings(bus: DynamixelBus, spec: RobotSpec, cal: CalibrationFile | None = None,
                   baud: int | None = None) -> list[Difference]:
    """The settings items that differ from `expected_settings` (empty: all good)."""
    check_servos(bus, list(spec.joints))
    held = read_items(bus, spec, SETTINGS)
    return _diff(spec, held, expected_settings(spec, baud or bus.baud, cal), SETTINGS)


def apply(bus: DynamixelBus, spec: RobotSpec, diffs: list[Difference]) -> None:
    """Write the expected values of ``diffs`` (torque off first; Baud Rate last; each read back)."""
    if not diffs:
        return
    ids = sorted({d.servo_id for d in diffs})
    bus.torque(ids, False)
    order = sorted(diffs, key=lambda d: (d.item == "baud_rate", d.item != "homing_offset", d.servo_id))
    new_baud = None
    for d in order:
        if d.item == "baud_rate":
            table = bus.table(d.servo_id)
            bus.write(d.servo_id, "baud_rate", d.expected, raw=True)
            new_baud = table.baud_rates[d.expected]
            continue
        _write_limit_aware(bus, d)
    if new_baud is not None:
        bus.set_baud(new_baud)
        for i in ids:
            bus.ping(i, retries=2)


def _write_limit_aware(bus: DynamixelBus, d: Difference) -> None:
    """Position limits are checked against each other by the servo (min ≤ max): widen before narrowing."""
    if d.item in ("min_position_limit", "max_position_limit"):
        other = "max_position_limit" if d.item == "min_position_limit" else "min_position_limit"
        cur = bus.read(d.servo_id, other, raw=True)
        if (d.item == "min_position_limit" and d.expected > cur) or (d.item == "max_position_limit"
                                                                      and d.expected < cur):
            write_eeprom(bus, d.servo_id, other, 4095 if other == "max_position_limit" else 0)
    write_eeprom(bus, d.servo_id, d.item, d.expected)


# ----------------------------------------------------------------------------- calibration vs motors
def motor_calibration(bus: DynamixelBus, spec: RobotSpec) -> dict[str, dict[str, int]]:
    """What the motors hold of a calibration: {joint: {homing_offset, min/max_position_limit}}."""
    return read_items(bus, spec, CALIBRATED)


def diff_calibration(bus: DynamixelBus, spec: RobotSpec, cal: CalibrationFile) -> list[Difference]:
    """Items where the motors and the calibration file disagree (file values are ``expected``)."""
    cal.check(spec, f"calibration {cal.robot}/{cal.robot_id}", complete=False)
    info = check_servos(bus, [j for j in spec.joints if j.name in cal.joints])
    held = motor_calibration(bus, spec)
    want = {n: {"homing_offset": jc.offset, "min_position_limit": jc.range[0], "max_position_limit": jc.range[1]}
            for n, jc in cal.joints.items()}
    diffs = _diff(spec, held, want, CALIBRATED)
    for j in spec.joints:  # a swapped servo: report model and firmware too
        jc = cal.joints.get(j.name)
        if jc is not None and info[j.name][1] != jc.firmware:
            diffs.append(Difference(j.name, j.servo_id, "firmware", info[j.name][1], jc.firmware))
    return diffs


def apply_calibration(bus: DynamixelBus, spec: RobotSpec, cal: CalibrationFile, prefer: str,
                      path=None) -> tuple[list[Difference], CalibrationFile]:
    """Resolve `diff_calibration` by ``prefer`` = "file" (write the motors) or "motors" (rewrite the file
    at ``path``). Returns the differences resolved and the calibration now in force."""
    if prefer not in ("file", "motors"):
        raise ParameterError(f"--prefer must be 'file' or 'motors', got {prefer!r}")
    diffs = diff_calibration(bus, spec, cal)
    if not diffs:
        return [], cal
    if prefer == "file":
        apply(bus, spec, [d for d in diffs if d.item != "firmware"])
        left = [d for d in diff_calibration(bus, spec, cal) if d.item != "firmware"]
        if left:
            raise CommError(f"the motors still differ after writing: {left[0]}")
        return diffs, cal
    held = motor_calibration(bus, spec)
    info = check_servos(bus, [j for j in spec.joints if j.name in cal.joints])
    joints = {}
    for j in spec.joints:
        if j.name not in cal.joints:
            continue
        h = held[j.name]
        try:
            check_offset(j, h["homing_offset"])
            check_range(j, h["min_position_limit"], h["max_position_limit"])
        except CalibrationError as e:
            raise CalibrationError(f"the motors do not hold a valid calibration ({e}); nothing written") from None
        joints[j.name] = JointCalibration(id=j.servo_id, model=info[j.name][0], firmware=info[j.name][1],
                                          offset=h["homing_offset"], direction=j.direction,
                                          range=(h["min_position_limit"], h["max_position_limit"]))
    new = cal.with_joints(joints, spec)
    if path is None:
        raise ParameterError("apply --prefer motors needs the calibration file's path")
    save(new, path)
    return diffs, new
