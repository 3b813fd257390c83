"""What the command modules share to build their parsers: argument types, the bus options, the servo bus
opener (`felis.drivers.ports` from the parsed arguments) and command groups with sub-commands.

Every command module exposes ``register(sub)``, ``sub`` being the ``felis`` sub-parsers action (its
parsers report errors as one line, `felis.cli.main.Parser`); a learned skill's module also exposes
``register_train(sub)`` and ``register_eval(sub)`` for ``felis train``/``felis eval`` (`felis.cli.learn`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path

from felis.errors import ParameterError, UsageError


# ----------------------------------------------------------------------------- argument types
def finite(text: str) -> float:
    """A finite number."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return v


def size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` of a rendered video, within 16x16…1920x1080."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if not (16 <= w <= 1920 and 16 <= h <= 1080):
        raise argparse.ArgumentTypeError(f"size {w}x{h} outside 16x16…1920x1080")
    return w, h


def id_list(text: str) -> list[int]:
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


def one_id(text: str) -> int:
    """One servo ID."""
    found = id_list(text)
    if len(found) != 1:
        raise argparse.ArgumentTypeError(f"expected one servo ID, got {text!r}")
    return found[0]


def baud_rate(text: str) -> int:
    """A baud rate the SDK supports: ``1000000``, ``1M``, ``57.6k``, ``57_600``."""
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


# ----------------------------------------------------------------------------- the servo bus
def bus_args(sp, robot_default: str | None = None) -> None:
    """``--port``, ``--baud``, ``--robot`` (for a virtual bus), ``--json``: the operator commands' options."""
    sp.add_argument("--port", help="serial device, or 'virtual' for a virtual bus (default $FELIS_PORT)")
    sp.add_argument("--baud", type=baud_rate, default=1_000_000, help="baud rate (default 1000000)")
    sp.add_argument("--robot", default=robot_default, help="robot for --port virtual (default cat)")
    trace_option(sp)
    json_option(sp)


def trace_option(sp) -> None:
    """``--trace FILE``: write every bus packet, timed and decoded, to FILE (`felis.drivers.dynamixel.trace`)."""
    sp.add_argument("--trace", type=Path, metavar="FILE",
                    help="write every instruction and status packet (time, decoded, hex) to FILE")


def backend_args(sp, imu_help: str = "dxl: serial device of the cat's IMU (BNO08x UART-RVC)") -> None:
    """A run's robot: ``--backend sim|dxl`` and, for servos, ``--port``, ``--baud``, ``--imu-port``, ``--robot-id``,
    ``--calibration``, ``--yes`` (`felis.cli.episode.Episode` takes them)."""
    sp.add_argument("--backend", default="sim", choices=["sim", "dxl", "dynamixel"],
                    help="sim: MuJoCo; dxl: Dynamixel servos on --port (default sim)")
    sp.add_argument("--port", help="dxl: serial device, or 'virtual' (virtual bus backed by MuJoCo)")
    sp.add_argument("--baud", type=baud_rate, default=1_000_000, help="dxl: baud rate (default 1000000)")
    sp.add_argument("--imu-port", help=imu_help)
    sp.add_argument("--robot-id", help="dxl: use this robot's calibration (`felis calibrate --id`)")
    sp.add_argument("--calibration", type=Path, metavar="FILE", help="dxl: a calibration file instead of --robot-id")
    sp.add_argument("--yes", action="store_true", help="dxl: apply EEPROM setting differences without asking")


def live_option(sp, what: str = "serve the run live to Foxglove over WebSocket") -> None:
    """``--live [HOST:]PORT``: serve the run's log channels over the Foxglove WebSocket protocol
    (`felis.logs.live`); 127.0.0.1 unless a host is given; nothing listens without it."""
    sp.add_argument("--live", metavar="[HOST:]PORT",
                    help=f"{what} (127.0.0.1 unless HOST is given; 0: any free port)")


def json_option(sp) -> None:
    """``--json``: print the results as JSON (`felis.cli.output`) instead of text."""
    sp.add_argument("--json", action="store_true", help="print results as JSON")


def servo_command(sub, name: str, help: str, func) -> argparse.ArgumentParser:
    """A command on one servo: the bus options (`bus_args`), then the servo's ``id``; ``func`` runs it. Returns
    the parser, for the command's own arguments."""
    p = sub.add_parser(name, help=help)
    bus_args(p)
    p.add_argument("id", type=one_id)
    p.set_defaults(func=func)
    return p


def dry_run(p) -> None:
    """``--dry-run``: a command that writes checks everything and writes nothing."""
    p.add_argument("--dry-run", action="store_true", help="check everything, write nothing")


@contextlib.contextmanager
def open_bus(args, *, sim: bool = False, retries: int = 1, quiet_check: bool = True):
    """`felis.drivers.ports.open_ports` for ``--port``/``--baud``/``--robot`` (default cat) and, where the
    command has them, ``--imu-port`` and ``--trace``: a context manager giving `felis.drivers.ports.Ports` with
    the bus open; the trace is flushed and closed after the bus, whichever way the block is left."""
    from felis.drivers.dynamixel.trace import PacketTrace
    from felis.drivers.ports import open_ports
    path = getattr(args, "trace", None)
    with contextlib.ExitStack() as stack:
        trace = stack.enter_context(PacketTrace(path)) if path is not None else None
        yield stack.enter_context(open_ports(args.port, robot=getattr(args, "robot", None) or "cat", baud=args.baud,
                                             imu_port=getattr(args, "imu_port", None), sim=sim, retries=retries,
                                             quiet_check=quiet_check, trace=trace))


# ----------------------------------------------------------------------------- long runs
def restart_option(sp, where: str = "--workdir") -> None:
    """``--restart`` for a command that checkpoints into ``where`` (see `check_checkpoints`)."""
    sp.add_argument("--restart", action="store_true",
                    help=f"start over, replacing the checkpoints an earlier run left in {where} (a run refuses to "
                         "otherwise: --resume continues them)")


def has_checkpoints(folder: Path, marker: str | None = None) -> bool:
    """Whether ``folder`` holds an earlier run's checkpoints: the file ``marker`` in it, or (None) anything at all."""
    folder = Path(folder)
    if marker is not None:
        return (folder / marker).is_file()
    return folder.is_dir() and any(folder.iterdir())


def check_checkpoints(folder: Path, resume: bool, restart: bool, found: bool) -> None:
    """``--resume`` needs an earlier run's checkpoints in ``folder`` (``found``). And they are hours of work: where
    they are, a run starts only with ``--resume`` (continue them) or ``--restart`` (start over, replacing them); a
    forgotten flag is one line, not a lost night. Both flags at once are refused too."""
    if resume and restart:
        raise ParameterError("--resume continues the checkpointed run and --restart replaces it: give one of them")
    if resume and not found:
        raise ParameterError(f"--resume: no checkpoint in {folder}")
    if found and not (resume or restart):
        raise ParameterError(f"{folder} holds the checkpoints of an earlier run: --resume continues it, --restart "
                             "starts over and replaces them")


# ----------------------------------------------------------------------------- command groups
def group(sub, name: str, help: str, dest: str, metavar: str, **kw):
    """A command with sub-commands (``felis sim drop``); without one it is a usage error. Returns the
    group's sub-parsers action."""
    p = sub.add_parser(name, help=help, **kw)
    groupsub = p.add_subparsers(dest=dest, metavar=metavar)
    p.set_defaults(func=lambda a: missing(p))
    return groupsub


def missing(parser: argparse.ArgumentParser) -> int:
    raise UsageError(f"{parser.prog}: missing sub-command (see `{parser.prog} --help`)")
