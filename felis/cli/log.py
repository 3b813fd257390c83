"""``felis log info|plot|export``: a run log's summary (robot, duration, messages per topic, events), a one-page
PNG of its joints, commands, height and tilt, and its numbers as CSV files (`felis.logs`).
"""

from __future__ import annotations

from pathlib import Path

from felis.cli import output
from felis.cli.args import group


def register(sub) -> None:
    """Add ``felis log info`` and ``felis log plot``."""
    logsub = group(sub, "log", "inspect run logs (MCAP)", "log_command", "LOG_COMMAND")
    info = logsub.add_parser("info", help="summary of a log: robot, duration, messages, events")
    info.add_argument("file", type=Path)
    info.add_argument("--json", action="store_true", help="print as JSON")
    info.set_defaults(func=cmd_log_info)
    plot = logsub.add_parser("plot", help="plot joints, commands, height and tilt to PNG")
    plot.add_argument("file", type=Path)
    plot.add_argument("--out", type=Path, required=True, help="PNG file to write")
    plot.set_defaults(func=cmd_log_plot)
    export = logsub.add_parser("export", help="write the log's joints, commands, IMU, contacts and events as CSV")
    export.add_argument("file", type=Path)
    export.add_argument("--csv", type=Path, required=True, metavar="DIR", help="folder for the CSV files")
    export.set_defaults(func=cmd_log_export)


def cmd_log_info(args) -> int:
    from felis.logs.reader import log_info
    info = log_info(args.file)
    if args.json:
        output.print_json(info)
    else:
        console = output.console()
        for k, v in info.items():
            console.print(f"[bold]{k}[/]: {v}")
    return 0


def cmd_log_plot(args) -> int:
    from felis.logs.plot import plot_log
    out = plot_log(args.file, args.out)
    print(f"plot: {out}")
    return 0


def cmd_log_export(args) -> int:
    from felis.logs.export import export_csv
    for path in export_csv(args.file, args.csv):
        print(f"csv: {path}")
    return 0
