"""``felis monitor``: a live table of the servos' position, velocity, current, temperature, voltage and
errors, sampled with one sync read per tick; ``--csv``/``--mcap`` export every sample
(`felis.logs.monitorlog`). A servo that stops answering is a row saying so, not the end of the
monitor; Ctrl-C, SIGTERM or SIGHUP end it with a complete export and exit code 130.
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path

from felis.cli import output
from felis.cli.args import bus_args, id_list, live_option, open_bus
from felis.errors import CommError, ParameterError
from felis.shutdown import EXIT_INTERRUPTED

MONITOR_BLOCK = (126, 21)  # present current … present temperature (126..146)


def register(sub) -> None:
    """Add ``felis monitor`` to the ``felis`` sub-commands."""
    mo = sub.add_parser("monitor", help="live table of position, velocity, current, temperature, voltage, errors")
    bus_args(mo)
    mo.add_argument("--id", type=id_list, help="servo IDs (default: the --robot's, else every servo found)")
    mo.add_argument("--rate", type=float, default=30.0, help="samples per second (default 30)")
    mo.add_argument("--duration", type=float, help="seconds (default: until Ctrl-C)")
    mo.add_argument("--csv", type=Path, help="export samples to CSV")
    mo.add_argument("--mcap", type=Path, help="export samples to MCAP (/joint_states and /monitor)")
    live_option(mo)
    mo.set_defaults(func=cmd_monitor)


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
    from rich.live import Live

    from felis.files import check_target, prepare_parent
    from felis.logs.monitorlog import MonitorExport
    from felis.spec import load_spec
    if not 1 <= args.rate <= 1000:  # NaN fails too
        raise ParameterError(f"--rate must be 1…1000 Hz, got {args.rate}")
    if args.duration is not None and not 0 < args.duration <= 1e6:
        raise ParameterError(f"--duration must be a positive number of seconds, got {args.duration}")
    for out in (args.csv, args.mcap):
        if out is not None:
            check_target(out, "monitor export", ParameterError)
    for out in (args.csv, args.mcap):
        if out is not None:
            prepare_parent(out, "monitor export", ParameterError)
    with open_bus(args) as ports:
        bus = ports.bus
        ids = _monitor_ids(args, bus)
        joints = None
        if args.robot:
            by_id = {j.servo_id: j.name for j in load_spec(args.robot).joints}
            joints = [by_id.get(i, f"id{i}") for i in ids]
        view = None
        if args.live is not None:
            from felis.logs.live import LiveView

            view = LiveView(args.live)
            output.live(view.url)
        try:
            sink = MonitorExport(args.csv, args.mcap, ids, robot=args.robot, joints=joints, live=view)
        except BaseException:
            if view is not None:
                view.close()
            raise
        period = 1.0 / args.rate
        t0 = time.perf_counter()
        n = stale = 0
        missing = dict.fromkeys(ids, 0)  # readings with no reply, per servo
        interrupted = False
        rows: list[dict] = []
        live = None
        try:
            if not args.json and sys.stdout.isatty():
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
            if view is not None:
                view.close()
    elapsed = time.perf_counter() - t0
    silent = {i: k for i, k in missing.items() if k}
    summary = {"samples": n, "rate_hz": round(n / elapsed, 2) if elapsed > 0 else 0.0, "stale_readings": stale,
               "no_reply": silent, "ids": ids, "csv": str(args.csv) if args.csv else None,
               "mcap": str(args.mcap) if args.mcap else None, "last": rows if n else [],
               "interrupted": interrupted}
    output.out(args, summary, f"{n} samples at {summary['rate_hz']} Hz; {stale} stale readings"
               + (" (no reply: " + ", ".join(f"ID {i} {k}×" for i, k in silent.items()) + ")" if silent else "")
               + (f"; CSV {args.csv}" if args.csv else "") + (f"; MCAP {args.mcap}" if args.mcap else ""))
    if interrupted:
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

