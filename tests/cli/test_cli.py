"""The ``felis`` command line, end to end: the installed console script run as a subprocess.

Every command runs in its own ``tmp_path`` (nothing lands in the repository) with
``MUJOCO_GL=egl`` and no display, as on a headless bench machine or CI runner. Checked: help,
``doctor`` (plus its latency-timer and serial-permission checks on fake files), drops and their
physics (free fall √(2h/g)), a logged run read back by ``log info`` / ``log plot``, offscreen
rendering, the viewer's refusal without a display, the demo, and the error contract of
``felis/cli/main.py``: bad input prints exactly one ``error: …`` line, exits non-zero (2 for
usage, 1 for the rest), shows no traceback unless ``--debug``, and writes nothing.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from felis.cli.doctor import FAIL, INFO, OK, WARN, check_environment, check_latency, check_serial

G = 9.81
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"

_SCRIPT = Path(sys.executable).with_name("felis")
FELIS = [str(_SCRIPT)] if _SCRIPT.is_file() else [sys.executable, "-m", "felis.cli.main"]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MUJOCO_GL"] = "egl"
    env["COLUMNS"] = "200"  # rich wraps at 80 columns otherwise
    # the virtual bus serves from this (busy) test process: allow its thread a scheduling hiccup
    env.setdefault("FELIS_TIMEOUT_MARGIN_MS", "40")
    return env


def felis(cwd: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([*FELIS, *args], cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=timeout)


def ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"exit {r.returncode}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    return r


def tree(root: Path) -> set[str]:
    """Every path under ``root`` (hidden files and folders included)."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def words(text: str) -> str:
    return " ".join(text.split())


# --------------------------------------------------------------------------------------- help


@pytest.mark.parametrize("command, options", [
    ((), ["--debug", "--version", "doctor", "demo", "run", "sim", "log"]),
    (("sim",), ["drop", "render", "view"]),
    (("sim", "drop"), ["--robot", "--height", "--roll", "--pitch", "--yaw", "--controller", "--duration",
                       "--policy", "--log", "--video", "--json"]),
    (("sim", "render"), ["--out", "--fps", "--size", "--height", "--duration"]),
    (("log", "plot"), ["file", "--out"]),
    (("log", "info"), ["file", "--json"]),
    (("run",), ["controller", "--robot", "--backend", "--duration", "--log", "--clock", "--json"]),
    (("doctor",), ["--json"]),
    (("demo",), ["--out", "--no-video"]),
], ids=lambda v: " ".join(v) if isinstance(v, tuple) else None)
def test_help(tmp_path, command, options):
    r = ok(felis(tmp_path, *command, "--help"))
    assert r.stdout.startswith(f"usage: felis {' '.join(command)}".rstrip())
    for opt in options:
        assert opt in r.stdout, f"`felis {' '.join(command)} --help` does not mention {opt}"
    assert r.stderr == ""
    assert tree(tmp_path) == set()


def test_version(tmp_path):
    import felis as pkg

    assert ok(felis(tmp_path, "--version")).stdout.strip() == f"felis {pkg.__version__}"


def test_no_command_prints_help(tmp_path):
    r = felis(tmp_path)
    assert r.returncode == 2
    assert r.stdout.startswith("usage: felis")


# --------------------------------------------------------------------------------------- doctor


def test_doctor_json(tmp_path):
    r = felis(tmp_path, "doctor", "--json")
    checks = json.loads(r.stdout)
    assert isinstance(checks, list) and checks
    for c in checks:
        assert set(c) == {"name", "status", "detail", "fix"}
        assert c["status"] in (OK, WARN, FAIL, INFO)
        if c["status"] == FAIL:
            assert c["fix"], f"{c['name']}: a failure without a fix"
    by_name = {c["name"]: c for c in checks}
    assert by_name["mujoco offscreen"]["status"] == OK, by_name["mujoco offscreen"]
    assert "egl" in by_name["mujoco offscreen"]["detail"]
    # the subprocess runs without DISPLAY/WAYLAND_DISPLAY: the viewer cannot open, not an error
    assert by_name["display"]["status"] == WARN
    assert "sim render" in by_name["display"]["fix"]
    assert by_name["FELIS_BUS_WATCHDOG_MS"]["status"] == WARN  # the suite's 1 s (tests/conftest.py)
    serial = [c for c in checks if c["name"] == "serial ports" or c["name"].startswith("serial /dev/")]
    assert serial, "no serial-port check"
    failed = [c for c in checks if c["status"] == FAIL]
    assert r.returncode == (1 if failed else 0), r.stderr
    assert failed == [], f"doctor fails on this machine: {failed}"
    assert tree(tmp_path) == set()


def test_doctor_text(tmp_path):
    r = ok(felis(tmp_path, "doctor"))
    text = words(r.stdout)
    assert "mujoco offscreen" in text and "display" in text
    assert "fix:" in text  # the display warning comes with its fix


def _latency(sysfs: Path, dev: str, text: str) -> Path:
    (sysfs / dev).mkdir(parents=True)
    f = sysfs / dev / "latency_timer"
    f.write_text(text)
    return f


def test_check_latency_fake_sysfs(tmp_path):
    assert check_latency(sysfs=str(tmp_path)) == []  # no adapter, nothing to say
    slow = _latency(tmp_path, "ttyUSB0", "16\n")
    _latency(tmp_path, "ttyUSB1", "1")
    _latency(tmp_path, "ttyUSB2", "garbage\n")
    by_name = {c.name: c for c in check_latency(sysfs=str(tmp_path))}
    assert set(by_name) == {"latency ttyUSB0", "latency ttyUSB1", "latency ttyUSB2"}
    fail = by_name["latency ttyUSB0"]
    assert fail.status == FAIL
    assert "16 ms" in fail.detail
    assert "echo 1" in fail.fix and str(slow) in fail.fix
    assert by_name["latency ttyUSB1"].status == OK
    assert by_name["latency ttyUSB2"].status == WARN


def test_check_environment_names_each_bus_setting_and_warns_of_a_looser_deadman():
    assert check_environment({}) == [] and check_environment({"FELIS_BUS_WATCHDOG_MS": " "}) == []
    (wd,) = check_environment({"FELIS_BUS_WATCHDOG_MS": "1000"})
    assert wd.status == WARN and "stop 1 s after" in wd.detail and "shipped 0.1 s" in wd.detail and wd.fix
    (wd,) = check_environment({"FELIS_BUS_WATCHDOG_MS": "60"})
    assert wd.status == INFO and "0.06 s" in wd.detail
    bad, margin = check_environment({"FELIS_BUS_WATCHDOG_MS": "5", "FELIS_TIMEOUT_MARGIN_MS": "40"})
    assert bad.status == FAIL and "must be 20…2540" in bad.detail and "unset" in bad.fix
    assert margin.status == INFO and "40 ms of slack" in margin.detail
    (bad,) = check_environment({"FELIS_TIMEOUT_MARGIN_MS": "lots"})
    assert bad.status == FAIL and "must be 0…1000" in bad.detail and bad.fix


def test_check_serial_none():
    (c,) = check_serial([])
    assert c.name == "serial ports" and c.status == INFO and c.fix


def test_check_serial_permissions(tmp_path):
    port = tmp_path / "ttyUSB0"
    port.write_bytes(b"")
    port.chmod(0o600)
    (c,) = check_serial([str(port)])
    assert (c.name, c.status) == (f"serial {port}", OK)

    if os.geteuid() == 0:
        return  # root opens anything: the no-permission case cannot be produced here
    port.chmod(0o000)
    try:
        (c,) = check_serial([str(port)])
    finally:
        port.chmod(0o600)
    assert c.status == FAIL
    assert "permission" in c.detail
    assert "dialout" in c.fix


# --------------------------------------------------------------------------------------- sim drop


def _drop(tmp_path: Path, *args: str) -> dict:
    r = ok(felis(tmp_path, "sim", "drop", *args, "--json"))
    assert tree(tmp_path) == set()  # no output asked for, none written
    return json.loads(r.stdout)


@pytest.mark.parametrize("controller, rel_tol", [
    # the stand controller swings the tail down while the body falls upside-down, and the tail
    # touches first (~8 ms early at 1 m, 1.9%); under `hold` nothing moves: contact within a physics step
    ("stand", 0.05),
    ("hold", 0.01),
])
def test_drop_upside_down_lands_on_its_back(tmp_path, controller, rel_tol):
    out = _drop(tmp_path, "--height", "1", "--roll", "180", "--controller", controller)
    assert out["run"]["ok"] is True
    assert out["run"]["stopped"] == "duration"
    fall = math.sqrt(2 * 1.0 / G)
    assert out["drop"]["height_m"] == 1.0 and out["drop"]["roll_deg"] == 180.0
    assert out["drop"]["free_fall_s"] == pytest.approx(fall, abs=1e-3)
    landing = out["landing"]
    assert landing["on_feet"] is False
    assert landing["torso_contact"] is True
    assert landing["tilt_deg"] > 135
    assert landing["first_contact_s"] == pytest.approx(fall, rel=rel_tol)
    # impact speed of a free fall from 1 m: √(2gh) ≈ 4.43 m/s
    assert landing["impact_speed_ms"] == pytest.approx(math.sqrt(2 * G * 1.0), rel=0.05)


def test_drop_runs_the_landing_policy_it_names(tmp_path):
    """``felis sim drop`` drops the cat under the landing controller's default policy (``caps+library``), and
    ``--policy`` picks another, as `felis run landing --policy` does: upside down from 1 m (the README's drop) the
    default and the cap policy land on their feet, the motion library alone (open loop) lands on its back."""
    default = _drop(tmp_path, "--height", "1", "--roll", "180")
    caps = _drop(tmp_path, "--height", "1", "--roll", "180", "--policy", "caps")
    library = _drop(tmp_path, "--height", "1", "--roll", "180", "--policy", "library")
    assert default["run"]["controller"] == caps["run"]["controller"] == library["run"]["controller"] == "landing"
    assert default["landing"]["on_feet"] is True and caps["landing"]["on_feet"] is True
    assert library["landing"]["on_feet"] is False and library["landing"]["torso_contact"] is True


def test_drop_upright_lands_on_its_feet(tmp_path):
    out = _drop(tmp_path, "--height", "0.5")
    assert out["run"]["ok"] is True
    landing = out["landing"]
    assert landing["on_feet"] is True
    assert landing["feet_down"] >= 3 and landing["torso_contact"] is False
    assert landing["first_contact_s"] == pytest.approx(math.sqrt(2 * 0.5 / G), rel=0.02)
    assert out["drop"]["free_fall_s"] == pytest.approx(math.sqrt(2 * 0.5 / G), abs=1e-3)


# --------------------------------------------------------------------------------------- run + log


def test_run_then_log_info_and_plot(tmp_path):
    r = ok(felis(tmp_path, "run", "stand", "--robot", "arm", "--backend", "sim", "--duration", "1",
                 "--log", "X.mcap", "--json"))
    report = json.loads(r.stdout)
    assert report["run"]["ok"] is True and report["run"]["robot"] == "arm"
    assert report["run"]["ticks"] == 100
    assert report["files"] == {"log": "X.mcap"}
    assert "drop" not in report and "landing" not in report
    log = tmp_path / "X.mcap"
    assert log.read_bytes().startswith(MCAP_MAGIC)

    info = json.loads(ok(felis(tmp_path, "log", "info", "X.mcap", "--json")).stdout)
    assert info["robot"] == "arm"
    assert info["complete"] is True
    assert info["joints"] == ["joint1", "joint2", "joint3", "joint4", "gripper"]
    assert abs(info["counts"]["/joint_states"] - 100) <= 1
    assert abs(info["counts"]["/joint_commands"] - 100) <= 1
    assert info["counts"]["/tf"] == info["counts"]["/joint_states"] and info["counts"]["/robot"] == 1
    assert info["counts"]["/meta"] == 1 and info["counts"]["/summary"] == 1
    assert info["rate"] == pytest.approx(100, rel=0.01)
    assert info["summary"]["run"]["ok"] is True

    text = ok(felis(tmp_path, "log", "info", "X.mcap")).stdout
    assert "arm" in text and "complete" in text

    r = ok(felis(tmp_path, "log", "plot", "X.mcap", "--out", "p.png"))
    assert "p.png" in r.stdout
    assert (tmp_path / "p.png").read_bytes()[:8] == PNG_MAGIC
    assert tree(tmp_path) == {"X.mcap", "p.png"}  # no temporary files left behind


# --------------------------------------------------------------------------------------- render


def test_render_png_strip(tmp_path):
    import imageio.v2 as imageio

    r = ok(felis(tmp_path, "sim", "render", "--robot", "cat", "--height", "0.3", "--duration", "0.5",
                 "--size", "160x120", "--out", "strip.png"))
    assert "strip.png" in r.stdout
    out = tmp_path / "strip.png"
    assert out.read_bytes()[:8] == PNG_MAGIC
    img = imageio.imread(out)
    assert img.shape[0] == 120 and img.shape[1] % 160 == 0 and img.shape[1] >= 2 * 160  # frames side by side
    assert img.std() > 1  # not a blank image
    assert tree(tmp_path) == {"strip.png"}


def test_render_gif(tmp_path):
    r = ok(felis(tmp_path, "sim", "render", "--robot", "cat", "--height", "0.3", "--duration", "0.5",
                 "--size", "160x120", "--fps", "20", "--out", "v.gif", "--json"))
    res = json.loads(r.stdout)
    assert res["files"] == {"video": "v.gif"}
    # the landing controller (the default for a dropped cat) moves the legs to its touchdown posture while the
    # cat falls, so the first foot meets the floor a few milliseconds after free fall from 0.3 m would
    assert res["landing"]["first_contact_s"] == pytest.approx(math.sqrt(2 * 0.3 / G), rel=0.05)
    data = (tmp_path / "v.gif").read_bytes()
    assert data[:6] in (b"GIF89a", b"GIF87a")
    assert tree(tmp_path) == {"v.gif"}


# --------------------------------------------------------------------------------------- view


def test_view_without_display(tmp_path):
    r = felis(tmp_path, "sim", "view")
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error:") and "display" in lines[0]
    assert "sim render" in lines[0]  # says what to do instead
    assert tree(tmp_path) == set()


# --------------------------------------------------------------------------------------- demo


def test_demo(tmp_path):
    t0 = time.perf_counter()
    r = felis(tmp_path, "demo", "--out", "runs", timeout=180)
    wall = time.perf_counter() - t0
    print(f"\nfelis demo: {wall:.1f} s wall")
    ok(r)
    assert wall < 120, f"felis demo took {wall:.0f} s"
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1 and re.fullmatch(r"\d{8}-\d{6}(-\d+)?", runs[0].name), runs
    run = runs[0]
    assert {p.name for p in run.iterdir()} == {"drop.mcap", "drop.mp4", "drop.png", "stand_dxl.mcap",
                                              "stand_dxl.png", "arm_figure8.mcap", "arm_figure8.mp4",
                                              "arm_figure8.png", "push.json", "push_margin.png",
                                              "push.mp4", "hard_drop.mcap", "hard_drop.mp4",
                                              "hard_drop.png"}  # no temporaries
    mp4 = (run / "drop.mp4").read_bytes()
    assert len(mp4) > 1000 and mp4[4:8] == b"ftyp"
    assert (run / "drop.png").read_bytes()[:8] == PNG_MAGIC
    assert (run / "drop.mcap").read_bytes().startswith(MCAP_MAGIC)

    from felis.logs.reader import log_info, read_log

    # part 1: servo-in-the-loop through the virtual bus: the whole hardware path, 50 Hz wall clock
    bus = log_info(run / "stand_dxl.mcap")
    assert bus["complete"] is True
    assert bus["summary"]["run"]["ok"] and bus["summary"]["run"]["stale_ticks"] == 0
    data = read_log(run / "stand_dxl.mcap")
    assert data.meta["backend"] == "dxl" and data.quat is not None  # IMU through the emulated RVC line
    assert abs(data.q[-1] - data.cmd_q[-1]).max() < 0.1  # the joints followed the commands through the bus
    assert data.q[-1, data.joints.index("tail_pitch")] > 0.4
    # the cat in the scene from the body model: its geoms once, every body's pose each tick
    assert bus["counts"]["/robot"] == 1 and bus["counts"]["/tf"] == bus["counts"]["/joint_states"] > 0
    assert "virtual Dynamixel bus" in r.stdout

    info = log_info(run / "drop.mcap")
    assert info["robot"] == "cat" and info["complete"] is True
    landing = info["summary"]["landing"]
    assert landing["on_feet"] is True and landing["tilt_deg"] < 15  # tilted 56°, the motion library rights it
    text = words(r.stdout)
    verdicts = re.findall(r"landed (on its feet|on its back|on its side|upright but not on its feet)", text)
    assert verdicts == ["on its feet", "on its feet"], r.stdout  # the 56° drop and the hard drop
    # part 3: the hard drop, tilted 143° from 3 m, under the same library: on its feet too
    hard = log_info(run / "hard_drop.mcap")["summary"]
    assert hard["landing"]["on_feet"] is True and hard["landing"]["tilt_deg"] < 30
    assert read_log(run / "hard_drop.mcap").meta["drop"] == {"height_m": 3.0, "roll_deg": 145.0, "pitch_deg": -12.0,
                                                              "yaw_deg": 0.0}
    assert (run / "hard_drop.mp4").read_bytes()[4:8] == b"ftyp"
    assert str(run.relative_to(tmp_path)) in text  # tells where the outputs are
    assert "Traceback" not in r.stderr

    # part 4: the arm tracks a figure eight with the learned IK: commands exact, the measured tool near
    arm = log_info(run / "arm_figure8.mcap")
    assert arm["robot"] == "arm" and arm["complete"] is True
    track = arm["summary"]["controller"]
    assert track["frames"] > 500 and track["unreachable"] == 0 and track["invalid"] == 0
    assert track["command_error"]["max_mm"] < 1e-6 and track["tracking_error"]["median_mm"] <= 1.0  # measured 0.8
    assert (run / "arm_figure8.mp4").read_bytes()[4:8] == b"ftyp"

    # part 5: the standing cat pushed: it falls without a reaction, after an early alarm; the selector's
    # reaction keeps it up; the margin of stability is plotted with the alarm
    push = json.loads((run / "push.json").read_text())
    assert push["runs"]["none"]["fell"] and push["runs"]["none"]["lead_s"] >= 0.15
    assert not push["runs"]["selector"]["fell"] and push["runs"]["selector"]["strategy"] != "none"
    assert (run / "push_margin.png").read_bytes()[:8] == PNG_MAGIC
    assert (run / "push.mp4").read_bytes()[4:8] == b"ftyp"
    assert "balance monitor" in text


def test_plot_file_mode_like_other_outputs(tmp_path):
    ok(felis(tmp_path, "run", "hold", "--robot", "arm", "--duration", "0.2", "--log", "a.mcap"))
    ok(felis(tmp_path, "log", "plot", "a.mcap", "--out", "p.png"))
    assert (tmp_path / "p.png").stat().st_mode & 0o777 == (tmp_path / "a.mcap").stat().st_mode & 0o777


def test_demo_out_is_a_file(tmp_path):
    (tmp_path / "runs").write_text("not a directory")
    r = felis(tmp_path, "demo", "--out", "runs")
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "runs" in lines[0]
    assert tree(tmp_path) == {"runs"}


# --------------------------------------------------------------------------------------- bad input

_ARM = (Path(__file__).resolve().parents[2] / "felis" / "robots" / "arm.toml").read_text()

BAD_INPUT = [
    # id, input files, argv, exit code, words the message must contain
    ("duplicate-servo-id", {"bad.toml": _ARM.replace("id = 12\n", "id = 11\n")},
     ["run", "stand", "--robot", "bad.toml", "--backend", "sim", "--log", "out.mcap"],
     1, ["bad.toml", "joint.joint2.id", "11"]),
    ("unknown-description-key", {"bad.toml": "colour = 'red'\n" + _ARM},
     ["run", "stand", "--robot", "bad.toml", "--log", "out.mcap"], 1, ["bad.toml", "colour"]),
    ("not-toml", {"bad.toml": "schema = \n"},
     ["run", "stand", "--robot", "bad.toml", "--log", "out.mcap"], 1, ["bad.toml", "TOML"]),
    ("missing-description", {}, ["run", "stand", "--robot", "nothere.toml", "--log", "out.mcap"],
     1, ["nothere.toml"]),
    ("unknown-robot", {}, ["run", "stand", "--robot", "dog", "--backend", "sim", "--log", "out.mcap"],
     1, ["dog", "cat", "arm"]),
    ("unknown-robot-drop", {}, ["sim", "drop", "--robot", "dog", "--height", "1", "--log", "d.mcap"],
     1, ["dog"]),
    ("height-negative", {}, ["sim", "drop", "--height", "-1", "--log", "d.mcap", "--video", "d.gif"],
     1, ["height", "-1"]),
    ("height-zero", {}, ["sim", "drop", "--height", "0", "--log", "d.mcap", "--video", "d.mp4"], 1, ["height"]),
    ("height-too-high", {}, ["sim", "drop", "--height", "100", "--log", "d.mcap", "--video", "d.png"],
     1, ["height", "100"]),
    ("height-not-a-number", {}, ["sim", "drop", "--height", "abc", "--log", "d.mcap"], 2, ["--height", "abc"]),
    ("roll-nan", {}, ["sim", "drop", "--height", "1", "--roll", "nan", "--log", "d.mcap"], 2, ["--roll", "nan"]),
    ("roll-out-of-range", {}, ["sim", "drop", "--height", "1", "--roll", "400", "--log", "d.mcap"],
     1, ["roll", "400"]),
    ("height-missing", {}, ["sim", "drop", "--log", "d.mcap"], 2, ["--height"]),
    ("drop-fixed-arm", {}, ["sim", "drop", "--robot", "arm", "--height", "1", "--log", "d.mcap"], 1, ["arm"]),
    ("log-info-missing", {}, ["log", "info", "missing.mcap"], 1, ["missing.mcap"]),
    ("log-plot-missing", {}, ["log", "plot", "missing.mcap", "--out", "p.png"], 1, ["missing.mcap"]),
    ("log-info-not-mcap", {"notalog.mcap": "hello"}, ["log", "info", "notalog.mcap"], 1, ["notalog.mcap", "MCAP"]),
    ("log-plot-not-mcap", {"notalog.mcap": "hello"}, ["log", "plot", "notalog.mcap", "--out", "p.png"],
     1, ["notalog.mcap"]),
    ("run-log-suffix", {}, ["run", "stand", "--robot", "cat", "--log", "out.txt"], 1, ["out.txt", ".mcap"]),
    ("drop-log-suffix", {}, ["sim", "drop", "--height", "1", "--log", "out.txt"], 1, ["out.txt", ".mcap"]),
    ("drop-policy-missing", {}, ["sim", "drop", "--height", "1", "--policy", "nope.npz", "--log", "d.mcap"],
     1, ["nope.npz", "no such landing policy file"]),
    ("drop-policy-not-landing", {}, ["sim", "drop", "--height", "1", "--controller", "stand", "--policy", "caps",
                                     "--log", "d.mcap"], 1, ["--policy", "landing", "stand"]),
    ("render-policy-bad-caps", {"c.json": '{"format": "felis-landing-caps"}'},
     ["sim", "render", "--height", "1", "--policy", "c.json", "--out", "v.mp4"], 1, ["caps: c.json"]),
    ("render-suffix", {}, ["sim", "render", "--height", "0.3", "--duration", "0.5", "--out", "v.txt"],
     1, ["v.txt", ".mp4"]),
    ("render-size", {}, ["sim", "render", "--out", "v.mp4", "--size", "10x10"], 2, ["--size", "10x10"]),
    ("render-fps", {}, ["sim", "render", "--out", "v.mp4", "--fps", "0"], 1, ["fps"]),
    ("unknown-controller", {}, ["run", "dance", "--robot", "cat", "--log", "out.mcap"], 1, ["dance", "stand"]),
    ("duration-zero", {}, ["run", "stand", "--robot", "cat", "--duration", "0", "--log", "out.mcap"],
     1, ["duration"]),
    ("rate-too-high", {}, ["run", "stand", "--robot", "cat", "--rate", "5000", "--log", "o.mcap"], 1, ["rate", "5000"]),
    ("backend-dxl-no-port", {}, ["run", "stand", "--robot", "cat", "--backend", "dxl"], 1, ["--port"]),
    ("backend-dxl-missing-port", {}, ["run", "stand", "--robot", "cat", "--backend", "dxl", "--port", "/dev/ttyUSB99"],
     1, ["/dev/ttyUSB99", "does not exist"]),
    ("backend-unknown", {}, ["run", "stand", "--robot", "cat", "--backend", "ros"], 2, ["--backend", "ros"]),
    ("sim-no-subcommand", {}, ["sim"], 2, ["felis sim", "sub-command"]),
    ("log-no-subcommand", {}, ["log"], 2, ["felis log", "sub-command"]),
    ("unknown-command", {}, ["fly"], 2, ["fly"]),
    ("plot-suffix", {}, ["log", "plot", "missing.mcap", "--out", "p.txt"], 1, ["p.txt", ".png"]),
    ("log-under-a-file", {"afile": "x"}, ["run", "stand", "--robot", "cat", "--log", "afile/x.mcap"],
     1, ["afile", "is a file, not a directory"]),
    ("video-under-a-file", {"afile": "x"}, ["sim", "drop", "--height", "1", "--log", "ok.mcap",
                                             "--video", "afile/v.mp4"], 1, ["afile", "not a directory"]),
]


@pytest.mark.parametrize("files, argv, code, needles", [pytest.param(*c[1:], id=c[0]) for c in BAD_INPUT])
def test_bad_input_one_line_nothing_written(tmp_path, files, argv, code, needles):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    before = tree(tmp_path)
    r = felis(tmp_path, *argv)
    assert r.returncode == code, f"exit {r.returncode}, expected {code}; stderr: {r.stderr}"
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{r.stderr}"
    assert lines[0].startswith("error:"), lines[0]
    assert "Traceback" not in r.stderr and "internal" not in lines[0]
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    assert r.stdout == ""
    assert tree(tmp_path) == before, f"bad input wrote {tree(tmp_path) - before}"


@pytest.mark.parametrize("argv", [
    ["--debug", "sim", "drop", "--height", "-1", "--log", "d.mcap"],
    ["sim", "drop", "--height", "-1", "--log", "d.mcap", "--debug"],  # --debug after the sub-command
], ids=["before", "after"])
def test_debug_shows_traceback(tmp_path, argv):
    r = felis(tmp_path, *argv)
    assert r.returncode != 0
    assert "Traceback (most recent call last)" in r.stderr
    assert "ParameterError" in r.stderr and "drop height" in r.stderr
    assert "unrecognized arguments" not in r.stderr
    assert tree(tmp_path) == set()

