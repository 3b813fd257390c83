"""``felis``: the command line — the parser's root, dispatch, and the exit-code contract.

Every command group is a module of this package that adds itself to the parser through
``register(sub)`` (`COMMANDS`, in ``--help`` order); this module parses, runs the chosen command and
turns what escapes it into an exit code.

Every failure an operator can cause (bad arguments, unknown robot, malformed description, missing
file, invalid parameters) prints one line, ``error: …``, on stderr and exits non-zero (2 for usage, 1
for the rest); ``--debug`` shows the traceback instead. ``--json`` prints machine-readable results.

One shutdown path (`felis.shutdown`): SIGINT, SIGTERM and SIGHUP all unwind the command as a
``KeyboardInterrupt``, so torque goes off (and is read back), the log gets its summary and child
processes stop whichever way a command is stopped; an interrupted command exits 130.
"""

from __future__ import annotations

import argparse
import os
import sys

import felis
from felis.cli import (
    calib,
    demo,
    doctor,
    dxl,
    ik,
    learn,
    log,
    monitor,
    output,
    phase,
    pose,
    replay,
    run,
    servo,
    sim,
    sysid,
    table,
    teleop,
    virtualbus,
)
from felis.errors import FelisError, UsageError
from felis.shutdown import EXIT_INTERRUPTED, signals

EXIT_ERROR, EXIT_USAGE = output.EXIT_ERROR, output.EXIT_USAGE

# doctor, demo, run, replay, teleop, pose; the bus commands (find-port … monitor, dump/restore);
# virtual-bus; calibration (setup-motors …
# check-eeprom); sysid; phase; train and eval; ik; sim; log
COMMANDS = (doctor, demo, run, replay, teleop, pose, dxl, servo, table, monitor, virtualbus, calib, sysid, phase, learn,
            ik, sim, log)
SIMULATING = ("demo", "sim", "run", "virtual-bus")  # commands that may render: MUJOCO_GL=egl without a display


class Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line (no usage dump)."""

    def error(self, message: str):  # noqa: D401
        raise UsageError(f"{self.prog}: {message} (see `{self.prog} --help`)")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="felis", description="ROS-free robot control for Dynamixel servos and MuJoCo.")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    p.add_argument("--version", action="version", version=f"felis {felis.__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for command in COMMANDS:
        command.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]  # accepted anywhere, e.g. after the sub-command
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return EXIT_USAGE
        if args.command in SIMULATING and "MUJOCO_GL" not in os.environ and not doctor.has_display():
            os.environ["MUJOCO_GL"] = "egl"
        with signals():
            return int(args.func(args) or 0)
    except UsageError as e:
        if debug:
            raise
        output.error(str(e))
        return EXIT_USAGE
    except FelisError as e:
        if debug:
            raise
        output.error(str(e))
        return EXIT_ERROR
    except BrokenPipeError:  # output piped into e.g. `head`
        return 0
    except KeyboardInterrupt as e:
        output.error(f"interrupted ({getattr(e, 'signame', 'SIGINT')})")
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - the CLI's contract: one line unless --debug
        if debug:
            raise
        output.error(f"internal: {type(e).__name__}: {e} (run with --debug for the traceback)")
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
