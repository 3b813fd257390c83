"""The bench commands that change servos tell the truth (issue 19): the emergency stop reads itself back,
``torque on`` never makes a joint jump, ``set-id``/``set-baud`` on a noisy bus report what happened,
``monitor`` starts with a servo missing and ends cleanly on a signal, and bad input is one line on
stderr. Each command is a subprocess, as in an operator's shell, against `felis virtual-bus` in its own
process (the unmodified SDK on a pseudo-terminal)."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from felis.drivers.dynamixel.bus import DynamixelBus, port_holders
from felis.drivers.virtual import spawn

_SCRIPT = Path(sys.executable).with_name("felis")
FELIS = [str(_SCRIPT)] if _SCRIPT.is_file() else [sys.executable, "-m", "felis.cli.main"]
BAUD = 1_000_000


def _holds(proc, port: str) -> bool:
    """Whether ``proc`` holds ``port`` (the virtual bus's own process holds it too, from the start)."""
    return any(h.startswith(f"PID {proc.pid} ") for h in port_holders(port))


def _env() -> dict:
    env = dict(os.environ, MUJOCO_GL="egl")
    env.setdefault("FELIS_TIMEOUT_MARGIN_MS", "40")
    return env


def felis(*args: str, timeout: float = 60, stdin=subprocess.DEVNULL) -> subprocess.CompletedProcess:
    return subprocess.run([*FELIS, *args], env=_env(), capture_output=True, text=True, timeout=timeout, stdin=stdin)


def one_line_error(r: subprocess.CompletedProcess, code: int = 1) -> str:
    assert r.returncode == code, (r.returncode, r.stdout, r.stderr)
    assert r.stdout == "", r.stdout  # the reason goes to stderr, nothing to stdout
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    return r.stderr


@pytest.fixture
def vbus():
    with spawn("cat") as vb:
        yield vb


def _read(port: str, dxl_id: int, item: str, baud: int = BAUD) -> int:
    with DynamixelBus(port, baud, retries=3) as b:
        return b.read(dxl_id, item, raw=True)


# --------------------------------------------------------------------------------- the emergency stop
def test_torque_off_reads_itself_back(vbus):
    assert felis("torque", "on", "--id", "1-12", "--port", vbus.port).returncode == 0
    r = felis("torque", "off", "--port", vbus.port)
    assert r.returncode == 0, r.stderr
    assert "verified on servo(s) 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12" in r.stdout
    assert [_read(vbus.port, i, "torque_enable") for i in range(1, 13)] == [0] * 12


def test_torque_off_at_the_wrong_baud_rate_reports_failure(vbus):
    felis("torque", "on", "--id", "1-12", "--port", vbus.port)
    err = one_line_error(felis("torque", "off", "--port", vbus.port, "--baud", "57600"))
    assert "no servo answered at 57600 bps" in err and "torque state unknown" in err


def test_torque_off_on_a_dead_port_reports_failure(tmp_path):
    err = one_line_error(felis("torque", "off", "--port", str(tmp_path / "ttyUSB9")))
    assert "does not exist" in err


def test_torque_off_names_a_servo_that_does_not_answer():
    with spawn("cat", faults="remove=4") as vb:
        err = one_line_error(felis("torque", "off", "--port", vb.port, "--robot", "cat"))
    assert "no reply from servo(s) 4" in err and "unknown" in err


def test_torque_on_sets_goal_to_present_first(vbus):
    """A goal left far from the horn (by another tool) must not make the joint jump when torque comes on."""
    with DynamixelBus(vbus.port, BAUD) as b:
        b.write(2, "goal_position", 2600, raw=True)
        present = b.read(2, "present_position", raw=True)
    r = felis("torque", "on", "--id", "2", "--port", vbus.port)
    assert r.returncode == 0, r.stderr
    time.sleep(0.2)
    with DynamixelBus(vbus.port, BAUD) as b:
        assert b.read(2, "goal_position", raw=True) == present
        assert abs(b.read(2, "present_position", raw=True) - present) <= 1
        assert b.read(2, "torque_enable", raw=True) == 1


# --------------------------------------------------------------------------------- set-id / set-baud, noisy
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_set_id_on_a_noisy_bus_reports_what_is_true(seed):
    """60 % of replies lost: whatever the command says must be what the servos show afterwards."""
    with spawn("cat", faults="drop=0.6", seed=seed) as vb:
        r = felis("set-id", "5", "40", "--port", vb.port)
        vb_port = vb.port
        with DynamixelBus(vb_port, BAUD, retries=12) as b:
            at_new = b.try_ping(40, retries=12) is not None
            at_old = b.try_ping(5, retries=12) is not None
    if r.returncode == 0:
        assert "changed ID 5 → 40" in r.stdout and at_new and not at_old
    else:
        assert r.stderr.count("\n") == 1
        assert ("did not happen" in r.stderr and at_old and not at_new) or "did not answer" in r.stderr


def test_set_id_whose_reply_was_lost_is_reported_changed():
    """Seed 1 loses the status reply of the write itself (found by trying seeds; deterministic for a seed):
    the ID did change, and the command says so."""
    with spawn("cat", faults="drop=0.6", seed=1) as vb:
        r = felis("set-id", "5", "40", "--port", vb.port)
    assert r.returncode == 0 and "its status reply was lost" in r.stdout, (r.stdout, r.stderr)


@pytest.mark.parametrize("seed", [1, 2])
def test_set_baud_on_a_noisy_bus_reports_what_is_true(seed):
    with spawn("cat", faults="drop=0.6", seed=seed) as vb:
        r = felis("set-baud", "5", "57600", "--port", vb.port)
        with DynamixelBus(vb.port, 57600, retries=12) as b:
            at_new = b.try_ping(5, retries=12) is not None
    if r.returncode == 0:
        assert "set servo 5 to 57600 bps" in r.stdout and at_new
    else:
        assert r.stderr.count("\n") == 1 and not at_new


# --------------------------------------------------------------------------------- monitor
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_monitor_starts_with_a_missing_servo_and_a_signal_ends_it_with_a_complete_export(tmp_path, sig):
    out = tmp_path / "m.csv"
    with spawn("cat", faults="remove=3") as vb:
        proc = subprocess.Popen([*FELIS, "monitor", "--robot", "cat", "--port", vb.port, "--csv", str(out),
                                 "--duration", "60"], env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 3000):
            time.sleep(0.05)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=20)
        assert proc.returncode == 130, (stdout, stderr)
        assert [_read(vb.port, i, "torque_enable") for i in range(1, 13) if i != 3] == [0] * 11  # never powered
    assert "no reply: ID 3" in stdout
    rows = list(csv.DictReader(out.open()))
    assert rows and rows[-1]["id"] == "12"  # the last sample written whole
    assert {r["stale"] for r in rows if r["id"] == "3"} == {"True"}
    assert {r["stale"] for r in rows if r["id"] != "3"} == {"False"}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_at_a_calibration_prompt_ends_it_with_nothing_written(tmp_path, vbus, sig):
    env = dict(_env(), XDG_CONFIG_HOME=str(tmp_path / "config"))
    proc = subprocess.Popen([*FELIS, "calibrate", "--robot", "cat", "--id", "t1", "--port", vbus.port],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not _holds(proc, vbus.port):  # connected, at its first prompt
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    time.sleep(1.0)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 130, (out, err)
    assert err.strip() == f"error: interrupted ({sig.name})"
    assert [_read(vbus.port, i, "torque_enable") for i in range(1, 13)] == [0] * 12
    assert not [f for f in (tmp_path / "config").rglob("*") if f.is_file()]  # no calibration file, no partial one


# --------------------------------------------------------------------------------- one line for bad input
@pytest.mark.parametrize("args,needle", [
    (("write", "3", "goal_position", "1e308"), "out of range"),
    (("write", "3", "goal_position", "2000.7", "--raw"), "--raw needs an integer"),
    (("monitor", "--rate", "nan", "--duration", "1"), "--rate must be"),
    (("monitor", "--duration", "-5"), "--duration must be"),
    (("monitor", "--duration", "1", "--csv", "/proc/felis/x.csv"), "cannot write monitor export"),
])
def test_bad_input_on_a_bus_command_is_one_line(vbus, args, needle):
    assert needle in one_line_error(felis(*args, "--port", vbus.port))


def test_an_overflowing_baud_rate_is_a_usage_error():
    assert "not a baud rate" in one_line_error(felis("scan", "--port", "/dev/null", "--baud", "1e400"), code=2)


def test_find_port_unplug_needs_a_terminal():
    assert "needs a terminal" in one_line_error(felis("find-port", "--unplug"))


@pytest.mark.parametrize("args", [
    ("calibration", "import", "/dev/zero", "--robot", "cat", "--id", "x"),
    ("run", "stand", "--robot", "/dev/zero"),
    ("sim", "drop", "--height", "1", "--servo-params", "/dev/zero"),
    ("run", "arm-track", "--robot", "arm", "--trajectory", "/dev/zero"),
    ("log", "info", "/dev/zero"),
])
def test_endless_files_are_refused_at_once(args):
    t0 = time.monotonic()
    r = felis(*args)
    assert r.returncode in (1, 2) and r.stderr.count("\n") == 1, (r.stdout, r.stderr)
    assert time.monotonic() - t0 < 30


def test_oversized_file_is_refused_before_reading(tmp_path):
    big = tmp_path / "big.json"
    with open(big, "wb") as f:
        f.truncate(64 * 2**20)  # sparse: 64 MiB that cost nothing to make
    err = one_line_error(felis("calibration", "import", str(big), "--robot", "cat", "--id", "x"))
    assert "MiB is more than a calibration file can be" in err
