"""``felis doctor``: what this machine can do, each problem with a one-line fix.

Checks: Python and package versions, MuJoCo offscreen rendering (in a child process, since a
failing GL context can abort the process), a display for the viewer, USB serial adapters and the
permission to open them, the FTDI latency timer (16 ms by default caps a Dynamixel
request/response loop near 60 Hz; 1 ms is the fix), and the ``FELIS_*`` settings in the environment that change
how a run drives servos (a Bus Watchdog looser than the shipped 0.1 s is a warning).
"""

from __future__ import annotations

import glob
import os
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from felis.cli import output

OK, WARN, FAIL, INFO = "ok", "warn", "fail", "info"

_GL_PROBE = ("import mujoco; m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\".1\"/>"
             "</worldbody></mujoco>'); r = mujoco.Renderer(m, 32, 32); d = mujoco.MjData(m); "
             "mujoco.mj_forward(m, d); r.update_scene(d); r.render(); print('ok')")


@dataclass
class Check:
    name: str
    status: str
    detail: str
    fix: str = ""


def check_versions() -> list[Check]:
    from importlib import metadata

    import felis

    out = [Check("python", OK, sys.version.split()[0])]
    for mod, name in (("mujoco", "mujoco"), ("dynamixel_sdk", "dynamixel-sdk"), ("serial", "pyserial"),
                      ("numpy", "numpy")):
        try:
            __import__(mod)
            out.append(Check(name, OK, metadata.version(name)))
        except Exception as e:  # noqa: BLE001
            out.append(Check(name, FAIL, f"cannot import ({e})", f"pip install {name}  (or: make demo)"))
    out.append(Check("felis", OK, felis.__version__))
    return out


def check_gl() -> Check:
    backend = os.environ.get("MUJOCO_GL", "")
    env = dict(os.environ)
    if not backend and not has_display():
        env["MUJOCO_GL"] = backend = "egl"
    try:
        r = subprocess.run([sys.executable, "-c", _GL_PROBE], env=env, capture_output=True, text=True, timeout=60)
        ok = r.returncode == 0 and "ok" in r.stdout
        err = (r.stderr.strip().splitlines() or ["no output"])[-1]
    except subprocess.TimeoutExpired:
        ok, err = False, "timed out"
    label = backend or "default (GLFW)"
    if ok:
        return Check("mujoco offscreen", OK, f"renders with MUJOCO_GL={label}")
    return Check("mujoco offscreen", FAIL, f"MUJOCO_GL={label}: {err[:120]}",
                 "export MUJOCO_GL=egl and install EGL (Debian: apt-get install libegl1 libgl1 libopengl0)")


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_display() -> Check:
    if has_display():
        return Check("display", OK, os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY", ""))
    return Check("display", WARN, "none: `felis sim view` cannot open a window",
                 "use `felis sim render --out FILE.mp4`, or run on a machine with a display (ssh -X works)")


def serial_ports() -> list[str]:
    ports = sorted(set(glob.glob("/dev/ttyUSB*") + glob.glob("/dev/ttyACM*")))
    return ports


def check_serial(ports: list[str] | None = None) -> list[Check]:
    ports = serial_ports() if ports is None else ports
    if not ports:
        return [Check("serial ports", INFO, "no USB serial adapter found (/dev/ttyUSB*, /dev/ttyACM*)",
                      "plug in the U2D2/USB adapter; without hardware, use the simulation (--backend sim)")]
    out = []
    for p in ports:
        if os.access(p, os.R_OK | os.W_OK):
            out.append(Check(f"serial {p}", OK, "readable and writable"))
        else:
            out.append(Check(f"serial {p}", FAIL, "no permission to open",
                             "sudo usermod -aG dialout $USER, then log out and back in"))
    return out


def check_latency(sysfs: str = "/sys/bus/usb-serial/devices") -> list[Check]:
    out = []
    for f in sorted(glob.glob(f"{sysfs}/*/latency_timer")):
        dev = Path(f).parent.name
        try:
            ms = int(Path(f).read_text().strip())
        except (OSError, ValueError) as e:
            out.append(Check(f"latency {dev}", WARN, f"cannot read {f} ({e})"))
            continue
        if ms <= 1:
            out.append(Check(f"latency {dev}", OK, f"{ms} ms"))
        else:
            out.append(Check(f"latency {dev}", FAIL,
                             f"FTDI latency timer {ms} ms caps the control loop near {int(1000 / (ms + 1))} Hz",
                             f"echo 1 | sudo tee {f}   (permanent: a udev rule setting latency_timer=1)"))
    return out


def check_environment(environ=None) -> list[Check]:
    """One check per ``FELIS_*`` bus setting that is set (none: nothing to say)."""
    from felis.drivers.dynamixel.port import MARGIN_MS_PTY, MARGIN_MS_USB, MARGIN_MS_VIRTUAL, env_margin_ms
    from felis.drivers.dynamixel.robot import BUS_WATCHDOG_ENV, BUS_WATCHDOG_S, default_bus_watchdog_s
    from felis.errors import ParameterError

    env = os.environ if environ is None else environ
    out = []
    if env.get(BUS_WATCHDOG_ENV, "").strip():
        try:
            s = default_bus_watchdog_s(env)
        except ParameterError as e:
            out.append(Check(BUS_WATCHDOG_ENV, FAIL, f"{e}: every run on servos refuses to start",
                             f"unset {BUS_WATCHDOG_ENV} (the shipped {BUS_WATCHDOG_S:g} s), or give 20…2540"))
        else:
            detail = f"servos stop {s:g} s after the host's last packet (shipped {BUS_WATCHDOG_S:g} s)"
            out.append(Check(BUS_WATCHDOG_ENV, WARN, detail, f"unset {BUS_WATCHDOG_ENV} for the shipped deadman")
                       if s > BUS_WATCHDOG_S else Check(BUS_WATCHDOG_ENV, INFO, detail))
    if env.get("FELIS_TIMEOUT_MARGIN_MS"):
        try:
            ms = env_margin_ms(env)
        except ParameterError as e:
            out.append(Check("FELIS_TIMEOUT_MARGIN_MS", FAIL, f"{e}: every bus refuses to open",
                             f"unset FELIS_TIMEOUT_MARGIN_MS ({MARGIN_MS_PTY:g} ms on a pty, {MARGIN_MS_USB:g} ms on a "
                             f"USB adapter, {MARGIN_MS_VIRTUAL:g} ms on --port virtual), or give 0…1000"))
        else:
            out.append(Check("FELIS_TIMEOUT_MARGIN_MS", INFO, f"every reply timeout gets {ms:g} ms of slack "
                             f"(default {MARGIN_MS_PTY:g} ms on a pty, {MARGIN_MS_USB:g} ms on a USB adapter, "
                             f"{MARGIN_MS_VIRTUAL:g} ms on --port virtual)"))
    return out


def run_checks() -> list[Check]:
    return [*check_versions(), check_gl(), check_display(), *check_serial(), *check_latency(), *check_environment()]


def as_json(checks: list[Check]) -> list[dict]:
    return [asdict(c) for c in checks]


def register(sub) -> None:
    """Add ``felis doctor``."""
    d = sub.add_parser("doctor", help="check this machine: rendering, display, serial ports, latency timer")
    d.add_argument("--json", action="store_true", help="print results as JSON")
    d.set_defaults(func=cmd_doctor)


def cmd_doctor(args) -> int:
    checks = run_checks()
    if args.json:
        output.print_json(as_json(checks))
    else:
        console = output.console()
        style = {"ok": "green", "warn": "yellow", "fail": "red", "info": "cyan"}
        for c in checks:
            line = f"[{style[c.status]}]{c.status:>4}[/]  {c.name}: {c.detail}"
            if c.fix:
                line += f"\n      fix: {c.fix}"
            console.print(line)
    return output.EXIT_ERROR if any(c.status == FAIL for c in checks) else 0
