"""Operator commands for Dynamixel buses that read: find-port, scan, info, read, and write.

Every command takes ``--port PATH|virtual``, ``--baud`` and ``--json``. ``--port virtual`` starts a
virtual bus (``felis virtual-bus``) for ``--robot`` in a child process, so every command can be tried
with no hardware. The port also comes from ``$FELIS_PORT`` (`felis.drivers.ports`). The commands that
change a servo's state or address are in `felis.cli.servo`, the live monitor in `felis.cli.monitor`.

Guards, each one line and nothing written: unknown item names (with the nearest name), values out of
range (with the range in SI units), read-only items, EEPROM items while torque is on, a port that does
not exist or lacks permission.
"""

from __future__ import annotations

import sys

from felis.cli import output
from felis.cli.args import baud_rate, bus_args, dry_run, id_list, json_option, open_bus, servo_command
from felis.errors import CommError, ParameterError


def register(sub) -> None:
    """Add find-port, scan, info, read and write to the ``felis`` sub-commands."""
    fp = sub.add_parser("find-port", help="list serial ports; --unplug finds the adapter by unplugging it")
    fp.add_argument("--unplug", action="store_true", help="interactive: unplug the adapter to identify it")
    json_option(fp)
    fp.set_defaults(func=cmd_find_port)

    sc = sub.add_parser("scan", help="find servos: IDs and baud rates")
    bus_args(sc)
    sc.add_argument("--ids", type=id_list, help="IDs to ping, e.g. 1-20 (default: broadcast ping)")
    sc.add_argument("--bauds", type=lambda s: [baud_rate(x) for x in s.split(",")],
                    help="baud rates to try, comma-separated (default: all)")
    sc.set_defaults(func=cmd_scan)

    servo_command(sub, "info", "model, firmware, settings and state of one servo", cmd_info)

    rd = servo_command(sub, "read", "read a control-table item (SI units; --raw for raw)", cmd_read)
    rd.add_argument("item", help="item name, e.g. present_position")
    rd.add_argument("--raw", action="store_true", help="raw control-table value")

    wr = servo_command(sub, "write", "write a control-table item (EEPROM items need torque off)", cmd_write)
    wr.add_argument("item", help="item name, e.g. goal_position")
    wr.add_argument("value", help="value in SI units (rad, rad/s, A, V, s), a name for modes, or raw with --raw")
    wr.add_argument("--raw", action="store_true", help="VALUE is the raw control-table value")
    dry_run(wr)


def cmd_find_port(args) -> int:
    """List serial ports with their USB metadata; ``--unplug`` finds the adapter by unplugging it."""
    from serial.tools import list_ports  # late: pyserial's port listing, only for this command

    def ports() -> dict[str, dict]:
        out = {}
        for p in list_ports.comports():
            out[p.device] = {"device": p.device, "description": p.description, "manufacturer": p.manufacturer,
                             "vid": f"{p.vid:04x}" if p.vid is not None else None,
                             "pid": f"{p.pid:04x}" if p.pid is not None else None,
                             "serial_number": p.serial_number, "likely_dynamixel": _likely(p)}
        return out

    before = ports()
    if args.unplug:
        if args.json:
            raise ParameterError("--unplug is interactive; it cannot be combined with --json")
        if not sys.stdin.isatty():
            raise ParameterError("--unplug is interactive: it needs a terminal to wait for Enter (stdin is not one)")
        print("ports now: " + (", ".join(before) or "none"))
        input("unplug the Dynamixel adapter, then press Enter… ")
        after = ports()
        gone = sorted(set(before) - set(after))
        if not gone:
            raise CommError("no port disappeared; is the adapter plugged into this machine?")
        also = f" (also gone: {', '.join(gone[1:])})" if gone[1:] else ""
        print(f"the adapter is {gone[0]}; plug it back in{also}")
        return 0
    rows = list(before.values())
    if args.json:
        output.out(args, rows)
        return 0
    if not rows:
        print("no serial ports found; plug in the adapter (U2D2, OpenRB…) and check `dmesg | tail`")
        return 0
    for r in rows:
        mark = "  ← likely Dynamixel adapter" if r["likely_dynamixel"] else ""
        ids = f" [{r['vid']}:{r['pid']}]" if r["vid"] else ""
        print(f"{r['device']}: {r['description']}{ids}{mark}")
    print("not sure which? `felis find-port --unplug`")
    return 0


def _likely(p) -> bool:
    # FTDI FT232H (U2D2) 0403:6014, FT232R 0403:6001, ROBOTIS OpenRB/OpenCR 2f5d / 0483:5740
    return (p.vid, p.pid) in {(0x0403, 0x6014), (0x0403, 0x6001), (0x0483, 0x5740)} or p.vid == 0x2F5D


def cmd_scan(args) -> int:
    from felis.drivers.dynamixel.bus import SDK_BAUDS
    bauds = args.bauds or list(SDK_BAUDS)
    with open_bus(args) as ports:
        bus = ports.bus
        if args.json or not sys.stdout.isatty():
            found = bus.scan(ids=args.ids, bauds=bauds)
        else:
            with output.bar(quiet=False, counts=False) as prog:
                task = prog.add_task("scanning", total=1)

                def progress(done, total, label):
                    prog.update(task, completed=done, total=total, description=label)

                found = bus.scan(ids=args.ids, bauds=bauds, progress=progress)
    rows = [{"id": f.id, "baud": f.baud, "model": f.model, "model_number": f.model_number, "firmware": f.firmware}
            for f in found]
    if args.json:
        output.out(args, rows)
    elif not rows:
        print(f"no servos found at {', '.join(map(str, bauds))} bps; check power (the LED blinks at power-up) "
              "and cabling")
    else:
        for r in rows:
            print(f"ID {r['id']:3d}  {r['baud']:>7d} bps  {r['model']}  firmware {r['firmware']}")
        print(f"{len(rows)} servo(s)")
    return 0


INFO_ITEMS = ("model_number", "firmware_version", "id", "baud_rate", "return_delay_time", "drive_mode",
              "operating_mode", "homing_offset", "min_position_limit", "max_position_limit", "velocity_limit",
              "shutdown", "torque_enable", "led", "status_return_level", "hardware_error_status",
              "position_p_gain", "present_position", "present_velocity", "present_current", "present_load",
              "present_input_voltage", "present_temperature")


def _table(bus, dxl_id: int):
    """The servo's control table; a model felis has no table for is one line naming its Model Number."""
    from felis.drivers.dynamixel.controltable import unsupported
    try:
        return bus.table(dxl_id)
    except ParameterError:
        raise ParameterError(f"servo {dxl_id}: {unsupported(bus.ping(dxl_id).model_number)}") from None


def cmd_info(args) -> int:
    from felis.servos import hardware_error_names
    with open_bus(args) as ports:
        bus = ports.bus
        found = bus.ping(args.id)
        table = _table(bus, args.id)
        rows = []
        for name in INFO_ITEMS:
            if name not in table.items:
                continue
            it = table.items[name]
            raw = it.decode(bus.read_raw(args.id, it.addr, it.size))
            si = it.to_si(raw)
            rows.append({"item": name, "addr": it.addr, "raw": raw, "value": si, "unit": it.unit, "area": it.area})
        hw = next(r["raw"] for r in rows if r["item"] == "hardware_error_status")
    obj = {"id": args.id, "model": found.model, "firmware": found.firmware, "items": rows,
           "hardware_errors": hardware_error_names(hw)}
    if args.json:
        output.out(args, obj)
        return 0
    print(f"ID {args.id}: {found.model}, firmware {found.firmware}, {bus.baud} bps")
    for r in rows:
        v = r["value"]
        vs = f"{v:.4g} {r['unit']}".strip() if isinstance(v, float) else str(v)
        print(f"  {r['item']:<24s} {r['addr']:>4d}  raw {r['raw']:>8d}  {vs}")
    if hw:
        print(f"  hardware errors: {', '.join(hardware_error_names(hw))} (`felis reboot {args.id}` clears them)")
    return 0


def cmd_read(args) -> int:
    with open_bus(args) as ports:
        bus = ports.bus
        it = _table(bus, args.id).item(args.item)
        raw = it.decode(bus.read_raw(args.id, it.addr, it.size))
    value = raw if args.raw else it.to_si(raw)
    obj = {"id": args.id, "item": it.name, "raw": raw, "value": value, "unit": "" if args.raw else it.unit}
    output.out(args, obj, f"{value}" + ("" if args.raw or not it.unit else f" {it.unit}"))
    return 0


def _value(text: str):
    try:
        return float(text)
    except ValueError:
        return text  # enumerated items take names, e.g. operating_mode position


def cmd_write(args) -> int:
    value = _value(args.value)
    if args.raw:
        try:
            value = int(args.value, 0)  # raw values are integers: 2000.7 is refused, not truncated
        except ValueError:
            raise ParameterError(f"--raw needs an integer (e.g. 2048 or 0x800), got {args.value!r}") from None
    with open_bus(args) as ports:
        bus = ports.bus
        it = _table(bus, args.id).item(args.item)
        if it.values is not None and not args.raw and isinstance(value, float):
            value = int(value) if value.is_integer() else value
        raw = bus.write(args.id, args.item, value, raw=args.raw, dry_run=args.dry_run)
    verb = "would write" if args.dry_run else "wrote"
    output.out(args, {"id": args.id, "item": it.name, "raw": raw, "dry_run": args.dry_run},
                f"{verb} {it.name} = {raw} (raw) to servo {args.id}")
    return 0

