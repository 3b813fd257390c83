"""Joint calibration: the reference pose gives each servo's Homing Offset, a sweep gives its range.

For joint j with description zero ``z`` (rad of horn around tick 2048), the servo should read
``T = 2048 + z/(2π/4096)`` (`calfile.zero_tick`) when the robot is in the reference pose (every
joint at its MJCF zero; see docs/calibration.md for the cat's and the arm's). With Homing Offset
``H`` the servo reports Present Position ``P = raw + H``, so from a reading ``P`` taken under the
current offset ``H₀``::

    H = H₀ + (T − P)            must satisfy |H| ≤ 1024 (position mode)

Then the operator moves each joint through its whole travel; min and max of Present Position are
its range. A reading that jumps by more than half a turn between polls has wrapped across the
0/4095 seam and the range is refused, as are ranges under 2° wide, ranges without the reference
pose and ranges past the description's limits (`calfile.check_range`).

Operating modes: each servo must already run its joint's mode (the description's; `felis check-eeprom
--apply` sets it), else calibration stops before writing. In extended (4) and current-based position (5) mode
the servo counts turns from power-up, so Present Position does not wrap at 0/4095: a servo that has turned
since power-up is rebooted first (torque is off) so that its count starts again in one turn, as it will after
the next power cycle, and a sweep leaving one turn is refused for the same reason (after a power cycle the
servo would read that joint a turn off).

Everything is measured and checked before anything is written: Homing Offsets (EEPROM, torque off)
first, then Min/Max Position Limit, then the file (atomically, previous version kept). The
direction of each joint comes from the description.
"""

from __future__ import annotations

import time

from felis.calib.calfile import (
    CENTRE,
    CalibrationFile,
    JointCalibration,
    calibration_path,
    check_offset,
    check_range,
    check_robot_id,
    load,
    save,
    zero_tick,
)
from felis.calib.operator import Operator, SweepRow
from felis.calib.setup import select_joints
from felis.drivers.dynamixel.bus import DynamixelBus, NoReplyError
from felis.errors import CalibrationError, CommError
from felis.spec import JointSpec, RobotSpec

HOMING_OFFSET, MIN_LIMIT, MAX_LIMIT, PRESENT_POSITION = 20, 52, 48, 132
MULTI_TURN = (4, 5)  # operating modes whose Present Position counts turns (extended, current-based position)


def _i32(b: bytes) -> int:
    return int.from_bytes(b, "little", signed=True)


def check_servos(bus: DynamixelBus, joints: list[JointSpec]) -> dict[str, tuple[str, int]]:
    """Ping every joint's servo: {joint: (model, firmware)}; one line naming the missing or wrong ones."""
    from felis.drivers.dynamixel.bus import CorruptReplyError

    out, missing, wrong = {}, [], []
    for j in joints:
        try:
            f = bus.ping(j.servo_id, retries=2)
        except CorruptReplyError:
            raise CalibrationError(f"garbled replies from ID {j.servo_id} ({j.name}): two servos share that ID; "
                                   f"connect them one at a time with `felis setup-motors --motors {j.name}`") from None
        except NoReplyError:
            missing.append(f"{j.name} (ID {j.servo_id})")
            continue
        if f.model != j.servo:
            wrong.append(f"{j.name}: ID {j.servo_id} is a {f.model}, the description says {j.servo}")
        out[j.name] = (f.model, f.firmware)
    if missing:
        raise CalibrationError(f"no reply from {', '.join(missing)} at {bus.baud} bps on {bus.port_name}: check "
                               "power and cabling, or set the servo up with `felis setup-motors`")
    if wrong:
        raise CalibrationError("; ".join(wrong))
    return out


def read_i32(bus: DynamixelBus, joints: list[JointSpec], addr: int) -> dict[str, int]:
    """One signed 4-byte item of every joint's servo (sync read, all must answer)."""
    ids = [j.servo_id for j in joints]
    res = bus.sync_read(ids, addr, 4, fast=False, retries=2)
    lost = [j.name for j in joints if res.data[j.servo_id] is None]
    if lost:
        raise CommError(f"no reply from {', '.join(lost)} reading address {addr}")
    return {j.name: _i32(res.data[j.servo_id]) for j in joints}


def check_modes(bus: DynamixelBus, joints: list[JointSpec]) -> None:
    """Each servo runs its joint's operating mode (module doc); one line naming those that do not."""
    wrong = []
    for j in joints:
        mode = bus.read(j.servo_id, "operating_mode", raw=True)
        if mode != j.operating_mode:
            wrong.append(f"{j.name} (ID {j.servo_id}) runs mode {mode}, the description says {j.operating_mode}")
    if wrong:
        raise CalibrationError("; ".join(wrong) + ": run `felis check-eeprom --apply` first, then calibrate")


def restart_turn_count(bus: DynamixelBus, joints: list[JointSpec], operator: Operator | None = None) -> list[str]:
    """Reboot the servos of extended/current-based position joints whose reading has left one turn since
    power-up (module doc), so that they count from the encoder's one turn again; returns their names."""
    multi = [j for j in joints if j.operating_mode in MULTI_TURN]
    if not multi:
        return []
    held = read_i32(bus, multi, HOMING_OFFSET)
    present = read_i32(bus, multi, PRESENT_POSITION)
    turned = [j for j in multi if not 0 <= present[j.name] - held[j.name] <= 4095]
    for j in turned:
        bus.reboot(j.servo_id)
    for j in turned:  # a servo answers again once it has booted (tens of ms on hardware)
        deadline = time.monotonic() + 2.0
        while bus.try_ping(j.servo_id) is None:
            if time.monotonic() > deadline:
                raise CommError(f"joint {j.name}: servo {j.servo_id} did not answer within 2 s of its reboot")
            time.sleep(0.02)
    if turned and operator is not None:
        operator.say("rebooted " + ", ".join(j.name for j in turned) + ": they had turned since power-up and count "
                     "turns again from one")
    return [j.name for j in turned]


def homing_offsets(bus: DynamixelBus, joints: list[JointSpec]) -> dict[str, int]:
    """Homing Offsets that put each joint's current pose on its zero tick (checked, not written)."""
    held = read_i32(bus, joints, HOMING_OFFSET)
    present = read_i32(bus, joints, PRESENT_POSITION)
    out = {}
    for j in joints:
        h = held[j.name] + zero_tick(j) - present[j.name]
        check_offset(j, h)
        out[j.name] = h
    return out


def write_eeprom(bus: DynamixelBus, dxl_id: int, name: str, value: int) -> None:
    """Write an EEPROM item (torque must be off) and read it back."""
    bus.write(dxl_id, name, value, raw=True)
    back = bus.read(dxl_id, name, raw=True)
    if back != value:
        raise CommError(f"servo {dxl_id}: wrote {name} = {value}, reads back {back}")


class Sweep:
    """Min/position/max of Present Position per joint while the operator moves them."""

    def __init__(self, bus: DynamixelBus, joints: list[JointSpec]):
        self.bus, self.joints = bus, joints
        first = read_i32(bus, joints, PRESENT_POSITION)
        self.lo = dict(first)
        self.hi = dict(first)
        self.last = dict(first)
        self.seam = dict.fromkeys(first, False)

    def update(self) -> list[SweepRow]:
        try:
            now = read_i32(self.bus, self.joints, PRESENT_POSITION)
        except CommError:
            now = {}
        for name, p in now.items():
            if abs(p - self.last[name]) > CENTRE or not 0 <= p <= 4095:
                self.seam[name] = True  # wrapped across 0/4095 (position mode), or left one turn (modes 4, 5)
            self.lo[name] = min(self.lo[name], p)
            self.hi[name] = max(self.hi[name], p)
            self.last[name] = p
        return self.rows()

    def rows(self) -> list[SweepRow]:
        return [SweepRow(j.name, j.servo_id, self.lo[j.name], self.last[j.name], self.hi[j.name], self.seam[j.name])
                for j in self.joints]

    def ranges(self) -> dict[str, tuple[int, int]]:
        """The swept ranges, checked (`calfile.check_range`); a seam crossing is refused."""
        out = {}
        for j in self.joints:
            lo, hi = self.lo[j.name], self.hi[j.name]
            if self.seam[j.name] and j.operating_mode in MULTI_TURN:
                raise CalibrationError(f"joint {j.name}: the readings left one turn (0…4095) during the sweep; in "
                                       f"mode {j.operating_mode} the servo forgets its turn count at power-up and "
                                       "would then read this joint a turn off: remount the horn so the travel stays "
                                       "inside one turn, then calibrate again")
            if self.seam[j.name]:
                raise CalibrationError(f"joint {j.name}: the readings wrapped across the 0/4095 seam during the "
                                       "sweep; position mode cannot hold that range: remount the horn so the travel "
                                       "stays inside one turn, then calibrate again")
            check_range(j, lo, hi)
            out[j.name] = (lo, hi)
        return out


def calibrate(bus: DynamixelBus, spec: RobotSpec, robot_id: str, operator: Operator, *,
              joints: list[str] | None = None, path=None, sweep: bool = True) -> tuple[CalibrationFile, object]:
    """Calibrate ``joints`` (all by default) of robot ``robot_id``; returns (file contents, path written).

    A subset updates an existing file (the other joints are kept); calibrating a subset with no file
    yet is refused. ``sweep=False`` keeps the description's limits as the range (no sweep).
    """
    check_robot_id(robot_id)
    chosen = select_joints(spec, joints)
    path = path or calibration_path(spec.name, robot_id)
    previous = None
    try:
        previous = load(path, spec)  # the other joints and the IMU mounting are kept
    except CalibrationError as e:
        if len(chosen) < spec.n:
            raise CalibrationError(f"calibrating only {', '.join(j.name for j in chosen)} needs a complete file for "
                                   f"the rest: {e}") from None
    info = check_servos(bus, chosen)
    check_modes(bus, chosen)
    ids = [j.servo_id for j in chosen]
    bus.torque(ids, False)
    operator.wait(f"Put the {spec.name} in its reference pose (docs/calibration.md: every joint at its model zero) "
                  "and hold it still")
    restart_turn_count(bus, chosen, operator)
    held = read_i32(bus, chosen, HOMING_OFFSET)
    offsets = homing_offsets(bus, chosen)
    for j in chosen:
        write_eeprom(bus, j.servo_id, "homing_offset", offsets[j.name])
    try:
        return _after_zero(bus, spec, robot_id, operator, chosen, offsets, info, previous, path, sweep)
    except BaseException:  # refused range, lost servo, Ctrl-C: put the old offsets back, leave the file alone
        for j in chosen:
            try:
                bus.write(j.servo_id, "homing_offset", held[j.name], raw=True)
            except Exception:  # noqa: BLE001 - best effort; the original error is what the operator needs
                pass
        raise


def _after_zero(bus, spec, robot_id, operator, chosen, offsets, info, previous, path, sweep):
    # the servos now read their zero ticks in the reference pose
    after = read_i32(bus, chosen, PRESENT_POSITION)
    off = [f"{j.name} reads {after[j.name]}, expected {zero_tick(j)}" for j in chosen
           if abs(after[j.name] - zero_tick(j)) > 1]
    if off:
        raise CalibrationError("the reference pose moved while the offsets were written: " + "; ".join(off)
                               + "; hold the robot still and calibrate again")
    operator.say("zero set: " + ", ".join(f"{j.name} {offsets[j.name]:+d}" for j in chosen) + " ticks Homing Offset")
    if sweep:
        sw = Sweep(bus, chosen)
        operator.sweep(f"Move each joint of the {spec.name} ({', '.join(j.name for j in chosen)}) through its whole "
                       "travel, by hand, then back to the reference pose", sw.update)
        ranges = sw.ranges()
    else:
        from felis.calib.calfile import description_ticks

        ranges = {j.name: description_ticks(j) for j in chosen}
        for j in chosen:
            check_range(j, *ranges[j.name])
    for j in chosen:
        lo, hi = ranges[j.name]
        write_eeprom(bus, j.servo_id, "min_position_limit", lo)
        write_eeprom(bus, j.servo_id, "max_position_limit", hi)
    new = {j.name: JointCalibration(id=j.servo_id, model=info[j.name][0], firmware=info[j.name][1],
                                    offset=offsets[j.name], direction=j.direction, range=ranges[j.name])
           for j in chosen}
    if previous is not None:
        cal = previous.with_joints(new, spec)
    else:
        cal = CalibrationFile(robot=spec.name, robot_id=robot_id, joints=new)
    cal.check(spec, str(path))
    written = save(cal, path)
    operator.say(f"calibration written to {written}")
    return cal, written

