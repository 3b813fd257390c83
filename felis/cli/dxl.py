"""Operator commands for Dynamixel buses: find-port, scan, info, read, write, torque, reboot, set-id,
set-baud, monitor.

Every command takes ``--port PATH|virtual``, ``--baud`` and ``--json``. ``--port virtual`` starts a
virtual bus (``felis virtual-bus``) for ``--robot`` in a child process, so every command can be tried
with no hardware. The port also comes from ``$FELIS_PORT``.

Guards, each one line and nothing written: unknown item names (with the nearest name), values out of
range (with the range in SI units), read-only items, EEPROM items while torque is on, an ID change
onto an ID in use, a baud rate the servo lacks, a port that does not exist or lacks permission.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from felis.errors import CommError, ParameterError

MONITOR_BLOCK = (126, 21)  # present current … present temperature (126..146)


def _ids(text: str) -> list[int]:
    """``"1,2,5-8"`` -> [1, 2, 5, 6, 7, 8]."""
    out: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part:
                a, b = (int(x) for x in part.split("-", 1))
                out.extend(range(a, b + 1))
            elif part:
                out.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected IDs like 1,2,5-8, got {text!r}") from None
    bad = [i for i in out if not 0 <= i <= 252]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"servo IDs must be 0…252, got {text!r}")
    return out


def _id(text: str) -> int:
    ids = _ids(text)
    if len(ids) != 1:
        raise argparse.ArgumentTypeError(f"expected one servo ID, got {text!r}")
    return ids[0]


def _baud(text: str) -> int:
    from felis.drivers.dynamixel.bus import SDK_BAUDS

    t = text.lower().replace("_", "")
    mult = 1
    if t.endswith("m"):
        t, mult = t[:-1], 1_000_000
    elif t.endswith("k"):
        t, mult = t[:-1], 1000
    try:
        f = float(t) * mult
        if not math.isfinite(f) or f != int(f):
            raise ValueError(text)
        v = int(f)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a baud rate: {text!r}") from None
    if v not in SDK_BAUDS:
        raise argparse.ArgumentTypeError(f"baud rate {v} not supported; use one of {', '.join(map(str, SDK_BAUDS))}")
    return v


# ----------------------------------------------------------------------------- bus access
@contextlib.contextmanager
def open_bus(args, *, sim: bool = False, retries: int = 1, quiet_check: bool = True) -> Iterator:
    """The DynamixelBus for ``--port``; ``virtual`` spawns a virtual bus for ``--robot``.

    ``quiet_check``: listen 50 ms first and refuse a port that talks unprompted (the IMU's, given as the
    bus: `DynamixelBus.check_quiet`). The emergency stop skips it: it never waits before it sends."""
    from felis.drivers.dynamixel.bus import DynamixelBus

    port = args.port or os.environ.get("FELIS_PORT")
    if not port:
        raise ParameterError("no port: give --port PATH (see `felis find-port`) or --port virtual, or set FELIS_PORT")
    with contextlib.ExitStack() as stack:
        if port == "virtual":
            from felis.drivers.virtual import spawn

            vb = stack.enter_context(spawn(getattr(args, "robot", None) or "cat", sim=sim, baud=args.baud))
            port = vb.port
            args._imu_port = vb.imu_port
        bus = stack.enter_context(DynamixelBus(port, args.baud, retries=retries))
        if quiet_check:
            bus.check_quiet()
        yield bus


def _out(args, obj, human: str | None = None) -> None:
    if args.json:
        print(json.dumps(obj, indent=2, default=str))
    elif human is not None:
        print(human)


def _console():
    from rich.console import Console

    return Console(highlight=False, soft_wrap=True)


# ----------------------------------------------------------------------------- commands
def cmd_find_port(args) -> int:
    """List serial ports with their USB metadata; ``--unplug`` finds the adapter by unplugging it."""
    from serial.tools import list_ports

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
        _out(args, rows)
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
    with open_bus(args) as bus:
        if args.json or not sys.stdout.isatty():
            found = bus.scan(ids=args.ids, bauds=bauds)
        else:
            from rich.progress import Progress

            with Progress(transient=True) as prog:
                task = prog.add_task("scanning", total=1)

                def progress(done, total, label):
                    prog.update(task, completed=done, total=total, description=label)

                found = bus.scan(ids=args.ids, bauds=bauds, progress=progress)
    rows = [{"id": f.id, "baud": f.baud, "model": f.model, "model_number": f.model_number, "firmware": f.firmware}
            for f in found]
    if args.json:
        _out(args, rows)
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


def cmd_info(args) -> int:
    from felis.servos import hardware_error_names

    with open_bus(args) as bus:
        found = bus.ping(args.id)
        table = bus.table(args.id)
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
        _out(args, obj)
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
    with open_bus(args) as bus:
        it = bus.item(args.id, args.item)
        raw = it.decode(bus.read_raw(args.id, it.addr, it.size))
    value = raw if args.raw else it.to_si(raw)
    _out(args, {"id": args.id, "item": it.name, "raw": raw, "value": value, "unit": "" if args.raw else it.unit},
         f"{value}" + ("" if args.raw or not it.unit else f" {it.unit}"))
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
    with open_bus(args) as bus:
        it = bus.item(args.id, args.item)
        if it.values is not None and not args.raw and isinstance(value, float):
            value = int(value) if value.is_integer() else value
        raw = bus.write(args.id, args.item, value, raw=args.raw, dry_run=args.dry_run)
    verb = "would write" if args.dry_run else "wrote"
    _out(args, {"id": args.id, "item": it.name, "raw": raw, "dry_run": args.dry_run},
         f"{verb} {it.name} = {raw} (raw) to servo {args.id}")
    return 0


def cmd_torque(args) -> int:
    """Torque on or off, and read back: the emergency stop reports success only when it is true.

    ``off`` without ``--id``: a broadcast write, then Torque Enable read back from every servo the
    ``--robot`` description names or, without one, every servo a broadcast ping finds at this baud rate;
    none answering is a failure (torque state unknown), and so is a servo still on. ``on`` needs ``--id``;
    each servo's Goal Position is set to its Present Position first (no jump), then torque on, read back.
    """
    on = args.state == "on"
    with open_bus(args, quiet_check=on) as bus:  # the emergency stop never waits
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
            from felis.drivers.dynamixel.protocol import BROADCAST_ID

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
    _out(args, {"torque": args.state, "ids": check, "verified": True},
         f"torque {args.state}: verified on servo(s) {', '.join(map(str, check))}"
         + (" (broadcast, then read back)" if ids is None else ""))
    return 0


def _known_ids(args, bus) -> list[int]:
    """The servos an emergency stop checks: the --robot's, else whatever answers a broadcast ping."""
    if getattr(args, "robot", None):
        from felis.spec import load_spec

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
    with open_bus(args) as bus:
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
    _out(args, {"id": args.id, "rebooted": True, "hardware_errors": names},
         f"servo {args.id} rebooted; torque is off" + (f"; still reports {', '.join(names)}" if names else ""))
    return 0


def cmd_set_id(args) -> int:
    if args.id == args.new_id:
        raise ParameterError(f"servo already has ID {args.id}")
    if args.new_id > 252:
        raise ParameterError(f"IDs go up to 252, got {args.new_id}")
    with open_bus(args, retries=3) as bus:
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
    _out(args, {"old_id": args.id, "new_id": args.new_id, "dry_run": args.dry_run, "verified": not args.dry_run},
         f"{verb} ID {args.id} → {args.new_id}" + ("" if args.dry_run else f" ({f.model}, verified by ping{note})"))
    return 0


def cmd_set_baud(args) -> int:
    from felis.drivers.dynamixel.bus import baud_code

    with open_bus(args, retries=3) as bus:
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
    _out(args, {"id": args.id, "baud": args.new_baud, "code": code, "dry_run": args.dry_run,
                "verified": not args.dry_run},
         f"{verb} servo {args.id} to {args.new_baud} bps" + ("" if args.dry_run else f" ({f.model}, verified{note})"))
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


# ----------------------------------------------------------------------------- monitor
def monitor_rows(bus, ids: list[int]) -> list[dict]:
    """One sync read of Present Current … Present Temperature for ``ids``, in SI units."""
    from felis.servos import hardware_error_names

    res = bus.sync_read(ids, *MONITOR_BLOCK, fast=False)
    rows = []
    for i in ids:
        d = res.data[i]
        t = bus.models.get(i)
        if t is None and d is not None:
            with contextlib.suppress(CommError, ParameterError):
                t = bus.table(i)  # a servo that came back: learn its model
        if d is None or t is None:
            rows.append({"id": i, "stale": True})
            continue
        cur_item = t.items.get("present_current") or t.items["present_load"]
        row = {"id": i, "stale": False,
               "position": t.items["present_position"].to_si(int.from_bytes(d[6:10], "little", signed=True)),
               "velocity": t.items["present_velocity"].to_si(int.from_bytes(d[2:6], "little", signed=True)),
               cur_item.name.replace("present_", ""): cur_item.to_si(int.from_bytes(d[0:2], "little", signed=True)),
               "voltage": int.from_bytes(d[18:20], "little") * 0.1, "temperature": d[20],
               "status_error": res.errors.get(i, 0), "hardware_errors": []}
        if row["status_error"] & 0x80:
            with contextlib.suppress(CommError):
                row["hardware_errors"] = hardware_error_names(bus.hardware_error(i)[0])
        rows.append(row)
    return rows


def _monitor_ids(args, bus) -> list[int]:
    """The servos to watch: ``--id``, else the ``--robot``'s (models from its description: a missing servo
    is a row saying so, not a refusal to start), else every servo a broadcast ping finds."""
    from felis.spec import load_spec

    if args.robot:
        spec = load_spec(args.robot)
        for j in spec.joints:
            bus.register(j.servo_id, j.servo)
        ids = list(args.id) if args.id else [j.servo_id for j in spec.joints]
    elif args.id:
        ids = list(args.id)
        for i in ids:
            bus.try_ping(i, retries=1)  # learns the model of those that answer; the others show as missing
    else:
        ids = [f.id for f in bus.scan(bauds=[bus.baud])]
    if not ids:
        raise CommError(f"no servos answer on {bus.port_name} at {bus.baud} bps")
    return ids


def cmd_monitor(args) -> int:
    if not 1 <= args.rate <= 1000:  # NaN fails too
        raise ParameterError(f"--rate must be 1…1000 Hz, got {args.rate}")
    if args.duration is not None and not 0 < args.duration <= 1e6:
        raise ParameterError(f"--duration must be a positive number of seconds, got {args.duration}")
    from felis.files import check_target, prepare_parent

    for out in (args.csv, args.mcap):
        if out is not None:
            check_target(out, "monitor export", ParameterError)
    for out in (args.csv, args.mcap):
        if out is not None:
            prepare_parent(out, "monitor export", ParameterError)
    with open_bus(args) as bus:
        ids = _monitor_ids(args, bus)
        sink = _MonitorSink(args.csv, args.mcap, ids)
        period = 1.0 / args.rate
        t0 = time.perf_counter()
        n = stale = 0
        missing = dict.fromkeys(ids, 0)  # readings with no reply, per servo
        interrupted = False
        rows: list[dict] = []
        live = None
        try:
            if not args.json and sys.stdout.isatty():
                from rich.live import Live

                live = Live(auto_refresh=False)
                live.start()
            next_t = t0
            while args.duration is None or time.perf_counter() - t0 < args.duration:
                rows = monitor_rows(bus, ids)
                t = time.perf_counter() - t0
                n += 1
                stale += sum(r["stale"] for r in rows)
                for r in rows:
                    missing[r["id"]] += r["stale"]
                sink.write(t, rows)
                if live is not None:
                    live.update(_table(rows, n / max(t, 1e-9)), refresh=True)
                next_t += period
                time.sleep(max(0.0, next_t - time.perf_counter()))
        except KeyboardInterrupt:  # Ctrl-C, SIGTERM, SIGHUP (felis.shutdown): a complete export, then 130
            interrupted = True
        finally:
            if live is not None:
                live.stop()
            sink.close()
    elapsed = time.perf_counter() - t0
    silent = {i: k for i, k in missing.items() if k}
    summary = {"samples": n, "rate_hz": round(n / elapsed, 2) if elapsed > 0 else 0.0, "stale_readings": stale,
               "no_reply": silent, "ids": ids, "csv": str(args.csv) if args.csv else None,
               "mcap": str(args.mcap) if args.mcap else None, "last": rows if n else [],
               "interrupted": interrupted}
    _out(args, summary, f"{n} samples at {summary['rate_hz']} Hz; {stale} stale readings"
         + (" (no reply: " + ", ".join(f"ID {i} {k}×" for i, k in silent.items()) + ")" if silent else "")
         + (f"; CSV {args.csv}" if args.csv else "") + (f"; MCAP {args.mcap}" if args.mcap else ""))
    if interrupted:
        from felis.shutdown import EXIT_INTERRUPTED

        return EXIT_INTERRUPTED
    return 0


def _table(rows: list[dict], rate: float):
    from rich.table import Table

    tab = Table(title=f"felis monitor — {rate:.0f} Hz (Ctrl-C to stop)")
    for col in ("ID", "position (rad)", "velocity (rad/s)", "current/load", "temp (°C)", "voltage (V)", "errors"):
        tab.add_column(col, justify="right")
    for r in rows:
        if r["stale"]:
            tab.add_row(str(r["id"]), "—", "—", "—", "—", "—", "[red]no reply[/red]")
            continue
        cur = r.get("current", r.get("load"))
        err = ", ".join(r["hardware_errors"]) or ("alert" if r["status_error"] & 0x80 else "")
        tab.add_row(str(r["id"]), f"{r['position']:+.3f}", f"{r['velocity']:+.3f}", f"{cur:+.3f}",
                    str(r["temperature"]), f"{r['voltage']:.1f}", f"[red]{err}[/red]" if err else "")
    return tab


class _MonitorSink:
    """CSV (one row per servo per sample) and/or MCAP (topic /monitor, JSON) export."""

    FIELDS = ("t", "id", "stale", "position", "velocity", "current", "load", "temperature", "voltage",
              "status_error", "hardware_errors")

    def __init__(self, csv_path: Path | None, mcap_path: Path | None, ids: list[int]):
        self._csv_f = self._csv = self._mcap = self._mcap_f = None
        try:
            self._open(csv_path, mcap_path)
        except OSError as e:
            self.close()
            raise ParameterError(f"cannot write monitor export {e.filename}: {e.strerror or e}") from None

    def _open(self, csv_path: Path | None, mcap_path: Path | None) -> None:
        import csv

        if csv_path is not None:
            self._csv_f = open(csv_path, "w", newline="")
            self._csv = csv.DictWriter(self._csv_f, fieldnames=self.FIELDS, extrasaction="ignore")
            self._csv.writeheader()
        if mcap_path is not None:
            from mcap.writer import Writer

            self._mcap_f = open(mcap_path, "wb")
            self._mcap = Writer(self._mcap_f)
            self._mcap.start(profile="", library="felis monitor")
            schema = self._mcap.register_schema(name="felis.Monitor", encoding="jsonschema", data=json.dumps(
                {"type": "object", "properties": {"t": {"type": "number"}, "servos": {"type": "array"}}}).encode())
            self._chan = self._mcap.register_channel(topic="/monitor", message_encoding="json", schema_id=schema)
            self._t0 = time.time_ns()

    def write(self, t: float, rows: list[dict]) -> None:
        if self._csv is not None:
            for r in rows:
                self._csv.writerow({"t": f"{t:.4f}", **{k: (";".join(v) if isinstance(v, list) else v)
                                                       for k, v in r.items()}})
            self._csv_f.flush()
        if self._mcap is not None:
            ns = self._t0 + int(t * 1e9)
            self._mcap.add_message(self._chan, log_time=ns, publish_time=ns,
                                   data=json.dumps({"t": t, "servos": rows}).encode())

    def close(self) -> None:
        if self._csv_f is not None:
            self._csv_f.close()
        if self._mcap is not None:
            self._mcap.finish()
            self._mcap_f.close()


# ----------------------------------------------------------------------------- parser
def register(sub, parser_class) -> None:
    """Add the operator commands to the ``felis`` sub-command parser."""

    def bus_args(sp, robot_default: str | None = None):
        sp.add_argument("--port", help="serial device, or 'virtual' for a virtual bus (default $FELIS_PORT)")
        sp.add_argument("--baud", type=_baud, default=1_000_000, help="baud rate (default 1000000)")
        sp.add_argument("--robot", default=robot_default, help="robot for --port virtual (default cat)")
        sp.add_argument("--json", action="store_true", help="print results as JSON")

    fp = sub.add_parser("find-port", help="list serial ports; --unplug finds the adapter by unplugging it")
    fp.add_argument("--unplug", action="store_true", help="interactive: unplug the adapter to identify it")
    fp.add_argument("--json", action="store_true", help="print results as JSON")
    fp.set_defaults(func=cmd_find_port)

    sc = sub.add_parser("scan", help="find servos: IDs and baud rates")
    bus_args(sc)
    sc.add_argument("--ids", type=_ids, help="IDs to ping, e.g. 1-20 (default: broadcast ping)")
    sc.add_argument("--bauds", type=lambda s: [_baud(x) for x in s.split(",")],
                    help="baud rates to try, comma-separated (default: all)")
    sc.set_defaults(func=cmd_scan)

    info = sub.add_parser("info", help="model, firmware, settings and state of one servo")
    bus_args(info)
    info.add_argument("id", type=_id)
    info.set_defaults(func=cmd_info)

    rd = sub.add_parser("read", help="read a control-table item (SI units; --raw for raw)")
    bus_args(rd)
    rd.add_argument("id", type=_id)
    rd.add_argument("item", help="item name, e.g. present_position")
    rd.add_argument("--raw", action="store_true", help="raw control-table value")
    rd.set_defaults(func=cmd_read)

    wr = sub.add_parser("write", help="write a control-table item (EEPROM items need torque off)")
    bus_args(wr)
    wr.add_argument("id", type=_id)
    wr.add_argument("item", help="item name, e.g. goal_position")
    wr.add_argument("value", help="value in SI units (rad, rad/s, A, V, s), a name for modes, or raw with --raw")
    wr.add_argument("--raw", action="store_true", help="VALUE is the raw control-table value")
    wr.add_argument("--dry-run", action="store_true", help="check everything, write nothing")
    wr.set_defaults(func=cmd_write)

    tq = sub.add_parser("torque", help="torque on/off (off without --id: every servo, broadcast)")
    bus_args(tq)
    tq.add_argument("state", choices=["on", "off"])
    tq.add_argument("--id", type=_ids, help="servo IDs, e.g. 1,2,5-8")
    tq.set_defaults(func=cmd_torque)

    rb = sub.add_parser("reboot", help="reboot a servo (clears hardware-error shutdown)")
    bus_args(rb)
    rb.add_argument("id", type=_id)
    rb.set_defaults(func=cmd_reboot)

    si = sub.add_parser("set-id", help="change a servo's ID (refuses an ID in use)")
    bus_args(si)
    si.add_argument("id", type=_id)
    si.add_argument("new_id", type=_id)
    si.add_argument("--dry-run", action="store_true", help="check everything, write nothing")
    si.set_defaults(func=cmd_set_id)

    sb = sub.add_parser("set-baud", help="change a servo's baud rate (verified by ping at the new rate)")
    bus_args(sb)
    sb.add_argument("id", type=_id)
    sb.add_argument("new_baud", type=_baud)
    sb.add_argument("--dry-run", action="store_true", help="check everything, write nothing")
    sb.set_defaults(func=cmd_set_baud)

    mo = sub.add_parser("monitor", help="live table of position, velocity, current, temperature, voltage, errors")
    bus_args(mo)
    mo.add_argument("--id", type=_ids, help="servo IDs (default: the --robot's, else every servo found)")
    mo.add_argument("--rate", type=float, default=30.0, help="samples per second (default 30)")
    mo.add_argument("--duration", type=float, help="seconds (default: until Ctrl-C)")
    mo.add_argument("--csv", type=Path, help="export samples to CSV")
    mo.add_argument("--mcap", type=Path, help="export samples to MCAP (topic /monitor)")
    mo.set_defaults(func=cmd_monitor)
