"""A servo's whole control table: ``felis dump``, ``felis restore`` and ``felis factory-reset``.

``dump`` reads every item (`felis.drivers.dynamixel.tabledump.read_table`, a few block reads) and prints it,
or writes it as JSON with ``--out``. ``restore FILE`` shows the differences between the servo and a dump,
asks (y/N) unless ``--yes``, writes only the writable items that differ (never the ID, baud rate, protocol,
Torque Enable or the Indirect Data views: `tabledump.KEPT`), reads the table back and says what is true.
``factory-reset`` sends FACTORY_RESET behind the same confirmation and pings the servo where it must
answer afterwards (`felis.drivers.dynamixel.factoryreset`).

Refused in one line, nothing written: a dump of another model (naming both), a malformed dump, a servo
that does not answer, EEPROM differences while torque is on (without ``--yes``: see `cmd_restore`), no
confirmation (declined, or no terminal to ask on and no ``--yes``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from felis.cli import output
from felis.cli.args import bus_args, dry_run, one_id, open_bus
from felis.drivers.dynamixel.factoryreset import KEEP, factory_reset, where_after
from felis.errors import ParameterError


def register(sub) -> None:
    """Add dump, restore and factory-reset to the ``felis`` sub-commands."""
    du = sub.add_parser("dump", help="read a servo's whole control table (raw and SI); --out FILE saves it as JSON")
    bus_args(du)
    du.add_argument("--id", type=one_id, required=True, help="servo ID")
    du.add_argument("--out", type=Path, metavar="FILE", help="write the dump here (.json) for `felis restore`")
    du.set_defaults(func=cmd_dump)

    rs = sub.add_parser("restore", help="write a dump back: the writable items that differ, after a diff and a y/N")
    bus_args(rs)
    rs.add_argument("file", type=Path, help="a dump from `felis dump --out`")
    rs.add_argument("--id", type=one_id, help="servo to restore (default: the dump's ID); it keeps its own ID and baud")
    rs.add_argument("--yes", action="store_true", help="do not ask; with torque on, write the RAM items only")
    dry_run(rs)
    rs.set_defaults(func=cmd_restore)

    fr = sub.add_parser("factory-reset", help="FACTORY_RESET a servo (torque off), then find it by ping")
    bus_args(fr)
    fr.add_argument("--id", type=one_id, required=True, help="servo ID")
    fr.add_argument("--keep", choices=list(KEEP), default="id+baud",
                    help="what survives: id+baud (default), id (baud back to 57600), none (ID 1 at 57600)")
    fr.add_argument("--yes", action="store_true", help="do not ask")
    fr.set_defaults(func=cmd_factory_reset)


# ----------------------------------------------------------------------------- shared
def _confirm(args, question: str, refused: str) -> None:
    """Go on with ``--yes`` or a y on the terminal; else ParameterError ``refused`` (nothing written)."""
    if args.yes:
        return
    if not sys.stdin.isatty():
        raise ParameterError(f"{refused}: confirm with --yes (no terminal to ask on)")
    print(f"{question} [y/N] ", end="", file=sys.stderr, flush=True)
    if sys.stdin.readline().strip().lower() not in ("y", "yes"):
        raise ParameterError(f"{refused}: not confirmed")


def _value(v, unit: str) -> str:
    return f"{v:.6g} {unit}".strip() if isinstance(v, float) else f"{v} {unit}".strip()


def _torque_on(dump) -> bool:
    return "torque_enable" in dump.items and dump.raw("torque_enable") == 1


# ----------------------------------------------------------------------------- dump
def cmd_dump(args) -> int:
    from rich.table import Table

    from felis.drivers.dynamixel.tabledump import read_table
    output.check_json_out(args.out)
    with open_bus(args) as ports:
        dump = read_table(ports.bus, args.id)
    doc = dump.as_dict()
    output.write_json_out(args.out, doc)
    t = Table(title=f"ID {dump.id}: {dump.model} (model {dump.model_number}), firmware {dump.firmware}, "
                    f"{dump.baud} bps")
    for col, just in (("addr", "right"), ("item", "left"), ("area", "left"), ("access", "left"), ("raw", "right"),
                      ("value", "left")):
        t.add_column(col, justify=just)
    for it in dump.items.values():
        t.add_row(str(it.addr), it.name, it.area, it.access, str(it.raw), _value(it.value, it.unit))
    if args.out is not None and not args.json:
        t.caption = f"saved to {args.out}"
    output.out(args, doc, t)
    return 0


# ----------------------------------------------------------------------------- restore
def cmd_restore(args) -> int:
    """Restore a dump (module doc). With torque on, EEPROM items cannot be written: without ``--yes`` the
    restore is refused (nothing written); with ``--yes`` the RAM items are written, the EEPROM ones are
    reported as left, and the exit code is 1 (the servo is not in the dumped state)."""
    from felis.drivers.dynamixel.tabledump import apply_plan, kept_differences, load_dump, read_table, restore_plan
    dump = load_dump(args.file)
    dxl_id = dump.id if args.id is None else args.id
    with open_bus(args) as ports:
        bus = ports.bus
        found = bus.ping(dxl_id)
        if found.model_number != dump.model_number:
            raise ParameterError(f"{args.file} is a dump of a {dump.model} (model {dump.model_number}); servo {dxl_id} "
                                 f"is a {found.model} (model {found.model_number}): restore onto the same model")
        current = read_table(bus, dxl_id)
        plan = restore_plan(current, dump)
        kept = kept_differences(current, dump)
        eeprom = [c for c in plan if c.eeprom]
        torque = _torque_on(current)
        skipped = eeprom if torque else []
        todo = [c for c in plan if c not in skipped]
        _show_diff(args, dxl_id, plan, kept, torque)
        if torque and eeprom and not args.dry_run and (not args.yes or not todo):
            raise ParameterError(f"servo {dxl_id}'s torque is on: {len(eeprom)} EEPROM item(s) differ "
                                 f"({', '.join(c.item.name for c in eeprom[:4])}{' …' if len(eeprom) > 4 else ''}) "
                                 f"and can only be written with torque off; nothing written (`felis torque off "
                                 f"--id {dxl_id}`, then restore again; --yes writes the RAM items only)")
        doc = {"id": dxl_id, "model": dump.model, "file": str(args.file), "dry_run": args.dry_run,
               "changes": [c.as_dict() for c in plan], "kept": [c.as_dict() for c in kept],
               "not_written_torque_on": [c.item.name for c in skipped]}
        if args.dry_run or not todo:
            doc.update(restored=[], failed={})
            text = (f"would write {len(todo)} item(s) to servo {dxl_id}"
                    + (f"; {len(skipped)} EEPROM item(s) need torque off" if skipped else "")) if args.dry_run \
                else f"nothing to write: servo {dxl_id} already holds the dump's settings"
            output.out(args, doc, text)
            return 0
        _confirm(args, f"write {len(todo)} item(s) to servo {dxl_id}?", f"restore of {len(todo)} item(s) to servo "
                 f"{dxl_id} refused")
        result = apply_plan(bus, dxl_id, todo, current)
    doc.update(restored=result.restored, failed=result.failed)
    lines = [f"restored {len(result.restored)} of {len(todo)} item(s) on servo {dxl_id} (read back)"]
    lines += [f"  {name}: {why}" for name, why in result.failed.items()]
    if skipped:
        lines.append(f"  not written, torque on: {', '.join(c.item.name for c in skipped)}")
    output.out(args, doc, "\n".join(lines))
    if result.failed or skipped:
        what = (f"{len(result.failed)} item(s) did not take" if result.failed else "") + \
               ("; " if result.failed and skipped else "") + \
               (f"{len(skipped)} EEPROM item(s) left (torque on: `felis torque off --id {dxl_id}`, then restore "
                "again)" if skipped else "")
        output.error(f"servo {dxl_id} is not in the dumped state: {what}")
        return output.EXIT_ERROR
    return 0


def _show_diff(args, dxl_id: int, plan, kept, torque: bool) -> None:
    """The differences, before anything is written (on standard error with --json, so stdout stays JSON)."""
    from rich.table import Table

    from felis.drivers.dynamixel.tabledump import KEPT
    if args.json:
        return
    t = Table(title=f"servo {dxl_id}: current → dump")
    for col in ("item", "area", "current", "dump"):
        t.add_column(col)
    for c in plan:
        d = c.as_dict()
        t.add_row(c.item.name, c.item.area + (" (torque on: skipped)" if torque and c.eeprom else ""),
                  f"{_value(d['current_value'], c.item.unit)} ({c.current})",
                  f"{_value(d['dumped_value'], c.item.unit)} ({c.dumped})")
    for c in kept:
        t.add_row(c.item.name, c.item.area, str(c.current), f"{c.dumped} (not written)")
    if kept:
        t.caption = "not written: " + "; ".join(f"{c.item.name}: {KEPT[c.item.name]}" for c in kept)
    if plan or kept:
        output.console().print(t)


# ----------------------------------------------------------------------------- factory reset
def cmd_factory_reset(args) -> int:
    from felis.drivers.dynamixel.tabledump import read_table, restorable
    with open_bus(args, retries=3) as ports:
        bus = ports.bus
        found = bus.ping(args.id)
        table = bus.table(args.id)
        if bus.read(args.id, "torque_enable", raw=True):
            raise ParameterError(f"servo {args.id}'s torque is on and it refuses a factory reset; nothing sent "
                                 f"(`felis torque off --id {args.id}` first)")
        new_id, new_baud = where_after(table, args.id, bus.baud, args.keep)
        if (new_id, new_baud) != (args.id, bus.baud):
            _check_free(bus, new_id, new_baud, args.id)
        _confirm(args, f"factory-reset servo {args.id} ({found.model}), keeping {args.keep}: it will answer as ID "
                 f"{new_id} at {new_baud} bps?", f"factory reset of servo {args.id} refused")
        res = factory_reset(bus, args.id, args.keep)
        after = read_table(bus, res.id)
    # goal_position is not compared: at boot the servo sets it to the present position
    off = [it.name for it in table.items.values()
           if restorable(it) and it.name != "goal_position" and after.raw(it.name) != it.default]
    doc = {"id": args.id, "keep": args.keep, "option": res.option, "new_id": res.id, "new_baud": res.baud,
           "model": res.found.model, "verified": True, "reply_lost": res.reply_lost, "not_factory": off}
    note = "; its reply to the reset was lost" if res.reply_lost else ""
    extra = f"; {len(off)} setting(s) differ from the table's factory values: {', '.join(off)}" if off else ""
    output.out(args, doc, f"factory reset servo {args.id} ({res.found.model}, kept {args.keep}): answers as ID "
                          f"{res.id} at {res.baud} bps (verified by ping{note}){extra}")
    return 0


def _check_free(bus, new_id: int, new_baud: int, dxl_id: int) -> None:
    """Refuse a reset that would put the servo where another already answers (ID collision after it)."""
    old = bus.baud
    try:
        bus.set_baud(new_baud)
        other = bus.try_ping(new_id, retries=1)
    finally:
        bus.set_baud(old)
    if other is not None:
        raise ParameterError(f"after the reset servo {dxl_id} would answer as ID {new_id} at {new_baud} bps, where a "
                             f"{other.model} already answers; nothing sent (--keep id+baud, or disconnect the other)")
