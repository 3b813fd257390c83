"""Operator commands that change a servo and read back what is true: torque, reboot, set-id, set-baud.

Each takes ``--port PATH|virtual``, ``--baud``, ``--robot`` and ``--json`` (`felis.cli.args.bus_args`).
The emergency stop (``felis torque off``) reports success only when every servo reads back torque off;
an ID or baud-rate change whose reply was lost is judged by pinging (`_write_then_verify`). Guards,
each one line and nothing written: an ID change onto an ID in use, a baud rate the servo lacks.
"""

from __future__ import annotations

import time

from felis.cli import output
from felis.cli.args import baud_rate, bus_args, dry_run, id_list, one_id, open_bus, servo_command
from felis.errors import CommError, ParameterError


def register(sub) -> None:
    """Add torque, reboot, set-id and set-baud to the ``felis`` sub-commands."""
    tq = sub.add_parser("torque", help="torque on/off (off without --id: every servo, broadcast)")
    bus_args(tq)
    tq.add_argument("state", choices=["on", "off"])
    tq.add_argument("--id", type=id_list, help="servo IDs, e.g. 1,2,5-8")
    tq.set_defaults(func=cmd_torque)

    servo_command(sub, "reboot", "reboot a servo (clears hardware-error shutdown)", cmd_reboot)

    si = servo_command(sub, "set-id", "change a servo's ID (refuses an ID in use)", cmd_set_id)
    si.add_argument("new_id", type=one_id)
    dry_run(si)

    sb = servo_command(sub, "set-baud", "change a servo's baud rate (verified by ping at the new rate)", cmd_set_baud)
    sb.add_argument("new_baud", type=baud_rate)
    dry_run(sb)


def cmd_torque(args) -> int:
    """Torque on or off, and read back: the emergency stop reports success only when it is true.

    ``off`` without ``--id``: a broadcast write, then Torque Enable read back from every servo the
    ``--robot`` description names or, without one, every servo a broadcast ping finds at this baud rate;
    none answering is a failure (torque state unknown), and so is a servo still on. ``on`` needs ``--id``;
    each servo's Goal Position is set to its Present Position first (no jump), then torque on, read back.
    """
    from felis.drivers.dynamixel.protocol import BROADCAST_ID
    on = args.state == "on"
    with open_bus(args, quiet_check=on) as ports:  # the emergency stop never waits
        bus = ports.bus
        if args.id:
            ids = list(args.id)
        elif on:
            raise ParameterError("torque on needs --id (which servos to power); torque off without --id "
                                 "switches every servo off")
        else:
            ids = None
        if on:
            _goal_to_present(bus, ids)
        if ids is None:
            bus.write_raw(BROADCAST_ID, 64, b"\x00", "torque off (broadcast)")
            check = _known_ids(args, bus)
        else:
            bus.torque(ids, on)
            check = ids
        wrong, silent = _torque_back(bus, check, on)
        if wrong and not on:  # a lost write: once more to those still on
            bus.torque(wrong, False)
            wrong, silent = _torque_back(bus, check, on)
    if wrong or silent:
        parts = []
        if wrong:
            parts.append(f"torque is still {'off' if on else 'ON'} on servo(s) {', '.join(map(str, wrong))}"
                         + (" (a hardware-error shutdown? see `felis info ID`)" if on else ""))
        if silent:
            parts.append(f"no reply from servo(s) {', '.join(map(str, silent))}: their torque state is unknown")
        raise CommError("; ".join(parts))
    output.out(args, {"torque": args.state, "ids": check, "verified": True},
               f"torque {args.state}: verified on servo(s) {', '.join(map(str, check))}"
               + (" (broadcast, then read back)" if ids is None else ""))
    return 0


def _known_ids(args, bus) -> list[int]:
    """The servos an emergency stop checks: the --robot's, else whatever answers a broadcast ping."""
    from felis.spec import load_spec
    if getattr(args, "robot", None):
        return [j.servo_id for j in load_spec(args.robot).joints]
    found = sorted({f.id for f in bus.scan(bauds=[bus.baud])})
    if not found:
        raise CommError(f"no servo answered at {bus.baud} bps on {bus.port_name}: torque state unknown (another "
                        "baud rate? `felis scan` finds it; power? the servo LEDs blink at power-up)")
    return found


def _torque_back(bus, ids: list[int], on: bool) -> tuple[list[int], list[int]]:
    """(servos whose Torque Enable is not ``on``, servos that did not answer)."""
    back = bus.sync_read(ids, 64, 1, fast=False, retries=3)
    wrong = [i for i in ids if back.data[i] is not None and back.data[i][0] != int(on)]
    return wrong, back.stale


def _goal_to_present(bus, ids: list[int]) -> None:
    """Goal Position = Present Position on the servos in a position mode, so torque on holds them where
    they are (as `DynamixelRobot.arm` does)."""
    modes = bus.sync_read(ids, 11, 1, fast=False, retries=3)
    pos_ids = [i for i in ids if modes.data[i] is not None and modes.data[i][0] in (3, 4, 5)]
    present = bus.sync_read(pos_ids, 132, 4, fast=False, retries=3)
    missing = present.stale + modes.stale
    if missing:
        raise CommError(f"no reply from servo(s) {', '.join(map(str, sorted(set(missing))))}: torque stays off "
                        "(its position could not be read, and a goal left elsewhere would make the joint jump)")
    bus.sync_write(116, 4, {i: present.data[i] for i in pos_ids})


def cmd_reboot(args) -> int:
    with open_bus(args) as ports:
        bus = ports.bus
        bus.reboot(args.id)
        deadline = time.monotonic() + 2.0
        while True:  # the servo is deaf for a moment while it restarts
            f = bus.try_ping(args.id, retries=0)
            if f is not None or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        if f is None:
            raise CommError(f"servo {args.id} did not come back after reboot")
        bits, names = bus.hardware_error(args.id)
    output.out(args, {"id": args.id, "rebooted": True, "hardware_errors": names},
               f"servo {args.id} rebooted; torque is off" + (f"; still reports {', '.join(names)}" if names else ""))
    return 0


def cmd_set_id(args) -> int:
    if args.id == args.new_id:
        raise ParameterError(f"servo already has ID {args.id}")
    if args.new_id > 252:
        raise ParameterError(f"IDs go up to 252, got {args.new_id}")
    with open_bus(args, retries=3) as ports:
        bus = ports.bus
        bus.ping(args.id)
        other = bus.try_ping(args.new_id, retries=1)
        if other is not None:
            raise ParameterError(f"ID {args.new_id} is already used by a {other.model}; pick a free ID "
                                 "(`felis scan` lists them)")
        note = ""
        if args.dry_run:
            bus.write(args.id, "id", args.new_id, raw=True, dry_run=True)
        else:
            note = _write_then_verify(bus, lambda: bus.write(args.id, "id", args.new_id, raw=True),
                                      lambda: bus.try_ping(args.new_id, retries=3),
                                      lambda: bus.try_ping(args.id, retries=3),
                                      f"ID {args.id} → {args.new_id}")
            f = bus.ping(args.new_id, retries=3)
    verb = "would change" if args.dry_run else "changed"
    done = "" if args.dry_run else f" ({f.model}, verified by ping{note})"
    output.out(args, {"old_id": args.id, "new_id": args.new_id, "dry_run": args.dry_run, "verified": not args.dry_run},
               f"{verb} ID {args.id} → {args.new_id}" + done)
    return 0


def cmd_set_baud(args) -> int:
    from felis.drivers.dynamixel.bus import baud_code
    with open_bus(args, retries=3) as ports:
        bus = ports.bus
        table = bus.table(args.id)
        code = baud_code(table, args.new_baud)
        old = bus.baud
        note = ""
        if args.dry_run:
            bus.write(args.id, "baud_rate", code, raw=True, dry_run=True)
        else:
            def at(baud):
                def ping():
                    bus.set_baud(baud)
                    return bus.try_ping(args.id, retries=3)
                return ping

            note = _write_then_verify(bus, lambda: bus.write(args.id, "baud_rate", code, raw=True), at(args.new_baud),
                                      at(old), f"servo {args.id} to {args.new_baud} bps")
            bus.set_baud(args.new_baud)
            f = bus.ping(args.id, retries=3)
    verb = "would set" if args.dry_run else "set"
    done = "" if args.dry_run else f" ({f.model}, verified{note})"
    output.out(args, {"id": args.id, "baud": args.new_baud, "code": code, "dry_run": args.dry_run,
                      "verified": not args.dry_run}, f"{verb} servo {args.id} to {args.new_baud} bps" + done)
    return 0


def _write_then_verify(bus, write, new_answers, old_answers, what: str) -> str:
    """Write a setting that moves the servo (ID, baud rate), then say what is true.

    The servo acknowledges with its old ID at its old baud rate; on a noisy bus that status can be lost
    while the write took. So a write that got no reply is judged by pinging: at the new address it
    changed (returns a note saying the reply was lost), at the old one it did not (CommError), at
    neither the outcome is unknown (CommError)."""
    from felis.drivers.dynamixel.bus import CorruptReplyError, NoReplyError
    try:
        write()
        return ""
    except (NoReplyError, CorruptReplyError) as e:
        lost = e
    if new_answers() is not None:
        return "; its status reply was lost"
    if old_answers() is not None:
        raise CommError(f"{what} did not happen: the servo still answers as before ({lost})")
    raise CommError(f"{what}: no reply to the write and the servo answers neither as before nor as after; "
                    "`felis scan` shows where it is")

