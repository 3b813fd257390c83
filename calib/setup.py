"""Motor set-up: give each new servo its joint's ID and the robot's baud rate, one servo at a time.

New Dynamixels all answer as ID 1 at 57600 bps, so on a shared bus they collide. Set-up therefore
asks the operator to connect only one joint's servo, finds it (broadcast ping at the factory rate,
then the robot's rate, then every other rate), checks it is the model the description names, and
writes ID, then Baud Rate (both EEPROM, so torque goes off first), then verifies with a ping at the
new ID and rate. A servo already at its ID and rate is left as it is (idempotent); ``joints``
limits the run to a subset, and the rest of the robot is never touched.

Refused, with one line and nothing written: no servo answers; more than one answers; replies are
garbled (two servos on one ID: their replies collide on the wire); the wrong servo model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from felis.calib.operator import Operator
from felis.drivers.dynamixel.bus import SDK_BAUDS, CorruptReplyError, DynamixelBus, Found, baud_code
from felis.errors import CalibrationError, CommError, ParameterError
from felis.spec import JointSpec, RobotSpec

FACTORY_ID = 1
FACTORY_BAUD = 57_600


@dataclass
class MotorSetup:
    """What set-up did to one joint's servo."""

    joint: str
    id: int
    baud: int
    model: str
    firmware: int
    found_id: int
    found_baud: int
    changed: list[str] = field(default_factory=list)  # e.g. ["ID 1 → 5", "baud 57600 → 1000000"]

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def select_joints(spec: RobotSpec, names: list[str] | None) -> list[JointSpec]:
    """The description's joints named in ``names`` (all when None), in description order."""
    if not names:
        return list(spec.joints)
    unknown = [n for n in names if n not in spec.names]
    if unknown:
        raise ParameterError(f"{spec.name} has no joint {unknown[0]!r}; joints: {', '.join(spec.names)}")
    return [j for j in spec.joints if j.name in names]


def find_one(bus: DynamixelBus, bauds: list[int], probe_ids: list[int]) -> Found:
    """The single servo on the bus: searched rate by rate (``bauds`` in order), stopping at the first
    rate where anything answers. Raises `CalibrationError` for none, several or colliding servos."""
    for b in bauds:
        found = bus.scan(bauds=[b])
        if found:
            if len(found) > 1:
                raise CalibrationError(f"{len(found)} servos answer at {b} bps (IDs "
                                       f"{', '.join(str(f.id) for f in found)}): connect only one servo")
            return found[0]
        bus.set_baud(b)
        for i in probe_ids:  # nothing readable: are two servos talking over each other?
            try:
                bus.ping(i, retries=1)
            except CorruptReplyError:
                raise CalibrationError(f"garbled replies from ID {i} at {b} bps: two servos share ID {i}; connect "
                                       "only one servo") from None
            except CommError:
                continue
    raise CalibrationError(f"no servo answers on {bus.port_name} at any baud rate ({', '.join(map(str, bauds))}): "
                           "check power, the cable and that exactly one servo is connected")


def search_order(baud: int) -> list[int]:
    first = [FACTORY_BAUD] + ([baud] if baud != FACTORY_BAUD else [])
    return first + [b for b in SDK_BAUDS if b not in first]


def setup_motor(bus: DynamixelBus, j: JointSpec, baud: int) -> MotorSetup:
    """Find the one connected servo and make it joint ``j``'s: ID ``j.servo_id`` at ``baud``."""
    f = find_one(bus, search_order(baud), sorted({FACTORY_ID, j.servo_id}))
    if f.model != j.servo:
        raise CalibrationError(f"joint {j.name} needs a {j.servo}, the connected servo (ID {f.id}) is a {f.model}")
    res = MotorSetup(j.name, j.servo_id, baud, f.model, f.firmware, f.id, f.baud)
    bus.set_baud(f.baud)
    table = bus.table(f.id)
    code = baud_code(table, baud)
    if f.id != j.servo_id or f.baud != baud:
        bus.torque([f.id], False)
    cur = f.id
    if f.id != j.servo_id:
        bus.write(f.id, "id", j.servo_id, raw=True)
        cur = j.servo_id
        bus.ping(cur, retries=2)
        res.changed.append(f"ID {f.id} → {j.servo_id}")
    if f.baud != baud:
        bus.write(cur, "baud_rate", code, raw=True)
        bus.set_baud(baud)
        res.changed.append(f"baud {f.baud} → {baud}")
    bus.set_baud(baud)
    try:
        g = bus.ping(j.servo_id, retries=2)
    except CommError as e:
        raise CalibrationError(f"joint {j.name}: servo does not answer as ID {j.servo_id} at {baud} bps after "
                               f"set-up ({e}); power-cycle it and run set-up for {j.name} again") from None
    if g.model != j.servo:
        raise CalibrationError(f"joint {j.name}: ID {j.servo_id} now answers as a {g.model}, expected {j.servo}")
    return res


def setup_motors(bus: DynamixelBus, spec: RobotSpec, operator: Operator, *, joints: list[str] | None = None,
                 baud: int = 1_000_000) -> list[MotorSetup]:
    """Set up ``joints`` (all by default) one servo at a time; returns what was done per joint.

    Stops at the first servo that cannot be set up; the ones before it are done and stay done
    (set-up is idempotent, so running it again skips them).
    """
    if baud not in SDK_BAUDS:
        raise ParameterError(f"baud rate {baud} not supported; use one of {', '.join(map(str, SDK_BAUDS))}")
    chosen = select_joints(spec, joints)
    done = []
    for k, j in enumerate(chosen, 1):
        operator.wait(f"[{k}/{len(chosen)}] connect ONLY the servo of {j.name} ({j.servo}; it will become ID "
                      f"{j.servo_id} at {baud} bps), and disconnect every other servo")
        r = setup_motor(bus, j, baud)
        operator.say(f"{j.name}: " + (", ".join(r.changed) if r.changed else f"already ID {r.id} at {r.baud} bps")
                     + " — verified by ping")
        done.append(r)
    return done
