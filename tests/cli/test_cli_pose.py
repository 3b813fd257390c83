"""``felis pose`` end to end: teaching by hand on the virtual bus, and the pose file commands.

Real parts: the virtual bus serves a pseudo-terminal from this test process, the ``felis`` console script talks to
it through the unmodified dynamixel-sdk (a subprocess, like an operator's shell, answering its prompt on standard
input), calibration through `felis.calib.joints.calibrate`, and the scripted hand of `VirtualServo.hold_by_hand`
poses the robot while its torque is off. The pose file commands and the refusals run ``felis.cli.main.main``
in this process (the same parser, dispatch and one-line errors, without a process start each).

One encoder tick is 2π/4096 rad of horn (0.0879°), in joint units ``2π/4096 · m_per_rad``
(`felis.calib.poses.tick_in_joint_units`); the round trip compares the servos' Present Position ticks themselves.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import time

import numpy as np
import pytest
from test_cli import FELIS, _env, ok

from felis.calib.joints import calibrate
from felis.calib.operator import ScriptedOperator
from felis.calib.poses import PoseFile, load, poses_path, save, tick_in_joint_units
from felis.cli.main import main
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.virtual import VirtualBus
from felis.logs.reader import read_log
from felis.spec import load_spec

BAUD = 1_000_000


@pytest.fixture
def config_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    # the virtual bus serves from this (busy) test process: allow its thread a scheduling hiccup
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "40")
    return tmp_path / "config"


def _hand(vb, spec, q: dict[str, float] | None) -> None:
    """The operator's hands on every joint (None: they let go; the joints stay where they were left)."""
    for j in spec.joints:
        vb.servo(j.servo_id).hold_by_hand(None if q is None else q[j.name])


def _ticks(vb, spec) -> np.ndarray:
    return np.array([vb.servo(j.servo_id).get("present_position") for j in spec.joints])


def _torque(vb, spec) -> list[int]:
    return [vb.servo(j.servo_id).get("torque_enable") for j in spec.joints]


@pytest.fixture
def calibrated_cat(config_home):
    """A cat assembled with its horns up to ±30° off (uncalibrated), then calibrated as ``tabby``."""
    spec = load_spec("cat")
    rng = np.random.default_rng(7)
    offsets = {j.name: math.radians(float(rng.uniform(-30, 30))) for j in spec.joints}
    with VirtualBus.for_robot(spec, baud=BAUD, mount_offsets=offsets) as vb:
        zero = dict.fromkeys(spec.names, 0.0)
        with DynamixelBus(vb.port, BAUD, timeout_margin_ms=40, retries=2) as bus:
            calibrate(bus, spec, "tabby", ScriptedOperator(on_wait=lambda m: _hand(vb, spec, zero)), sweep=False)
        _hand(vb, spec, None)
        yield spec, vb


def _felis(*args: str, stdin: str | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([*FELIS, *args], env=_env(), input=stdin, capture_output=True, text=True, timeout=timeout)


def test_capture_by_hand_then_play_back_ends_on_the_captured_ticks(tmp_path, calibrated_cat):
    spec, vb = calibrated_cat
    rng = np.random.default_rng(11)
    taught = {j.name: float(rng.uniform(0.6 * j.lower, 0.6 * j.upper)) for j in spec.joints}
    _hand(vb, spec, taught)
    r = ok(_felis("pose", "capture", "crouch", "--robot", "cat", "--robot-id", "tabby", "--port", vb.port, "--json",
                  stdin="\n"))  # the operator presses Enter once the robot is posed
    assert "press Enter" in r.stderr  # the prompt (on stderr: stdout is the JSON)
    cap = json.loads(r.stdout)
    assert cap["torque_off_verified"] is True and cap["replaced"] is False
    assert _torque(vb, spec) == [0] * spec.n  # left off
    at_capture = _ticks(vb, spec)
    assert [cap["ticks"][n] for n in spec.names] == at_capture.tolist()
    tick = tick_in_joint_units(spec)
    got = np.array([cap["joints"][n] for n in spec.names])
    assert np.all(np.abs(got - np.array([taught[n] for n in spec.names])) <= tick)  # the hand's pose, to a tick
    stored = load(poses_path("cat", "tabby"), spec).poses["crouch"][1]
    assert stored == cap["joints"]

    # the hand moves the robot elsewhere and lets go
    _hand(vb, spec, {j.name: -0.5 * taught[j.name] for j in spec.joints})
    _hand(vb, spec, None)
    assert np.abs(_ticks(vb, spec) - at_capture).max() > 50

    log = tmp_path / "play.mcap"
    r = ok(_felis("pose", "play", "crouch", "--robot", "cat", "--robot-id", "tabby", "--backend", "dxl", "--port",
                  vb.port, "--durations", "0.6", "--settle", "0.4", "--rate", "50", "--log", str(log), "--json"))
    res = json.loads(r.stdout)
    assert res["run"]["ok"] and res["run"]["stopped"] == "duration" and res["run"]["torque_off_verified"] is True
    assert res["controller"]["keyframes"] == ["crouch"]
    after = _ticks(vb, spec)
    assert np.abs(after - at_capture).max() <= 1, (after - at_capture).tolist()  # measured: 0 on every servo
    assert _torque(vb, spec) == [0] * spec.n
    data = read_log(log)
    assert data.meta["controller"] == "keyframes" and data.complete
    assert np.abs(data.cmd_q[-1] - got).max() < 1e-9  # the last command is the captured pose itself


def test_ctrl_c_while_waiting_for_the_operator_stores_nothing_and_leaves_torque_off(calibrated_cat):
    spec, vb = calibrated_cat
    for j in spec.joints:  # someone left the robot powered
        vb.servo(j.servo_id).set("torque_enable", 1)
    proc = subprocess.Popen([*FELIS, "pose", "capture", "loaf", "--robot", "cat", "--robot-id", "tabby", "--port",
                             vb.port], env=_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        seen = ""
        while "press Enter" not in seen and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            seen += line
        assert "press Enter" in seen, seen + proc.stderr.read()
        assert _torque(vb, spec) == [0] * spec.n  # off (read back) before the operator is asked to move anything
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = [ln for ln in proc.stderr.read().splitlines() if ln.strip()]
    assert rc == 130 and err == ["error: interrupted (SIGINT)"]
    assert not poses_path("cat", "tabby").exists()
    assert _torque(vb, spec) == [0] * spec.n


# ----------------------------------------------------------------------------- the pose file commands, in process
def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _pose_file(spec, robot_id: str, **poses: np.ndarray) -> PoseFile:
    pf = PoseFile(robot=spec.name, robot_id=robot_id)
    for name, q in poses.items():
        pf = pf.with_pose(spec, name, q)
    return pf


def test_list_show_delete(capsys, config_home):
    spec = load_spec("cat")
    wave = np.linspace(-0.5, 0.5, spec.n)
    save(_pose_file(spec, "tabby", wave=wave, stand=0.5 * spec.pose("stand")), poses_path("cat", "tabby"))
    code, out, _ = _run(capsys, "pose", "list", "--robot", "cat", "--robot-id", "tabby", "--json")
    rows = json.loads(out)["poses"]
    assert code == 0 and [(r["name"], r["source"], r["overrides_description"]) for r in rows] == [
        ("wave", "file", False), ("stand", "file", True), ("zero", "description", False), ("sit", "description", False)]
    code, out, _ = _run(capsys, "calibration", "list", "--json")  # a pose file is not a calibration
    assert code == 0 and json.loads(out)["calibrations"] == []
    code, out, _ = _run(capsys, "pose", "list", "--robot", "cat")
    assert code == 0 and "wave" not in out and "description's poses only" in out

    code, out, _ = _run(capsys, "pose", "show", "wave", "--robot", "cat", "--id", "tabby", "--json")
    shown = json.loads(out)
    assert code == 0 and shown["source"] == "file" and list(shown["joints"].values()) == wave.tolist()
    code, out, _ = _run(capsys, "pose", "show", "sit", "--robot", "cat", "--robot-id", "tabby")
    assert code == 0 and out.startswith("sit (description)") and "hl_pitch" in out

    code, out, _ = _run(capsys, "pose", "delete", "wave", "--robot", "cat", "--robot-id", "tabby")
    assert code == 0 and "deleted pose 'wave'" in out
    path = poses_path("cat", "tabby")
    assert list(load(path, spec).poses) == ["stand"]
    assert list(load(path.with_name(path.name + ".bak"), spec).poses) == ["wave", "stand"]  # the previous version
    code, _, err = _run(capsys, "pose", "delete", "wave", "--robot", "cat", "--robot-id", "tabby")
    assert code == 1 and err == "error: no taught pose 'wave' for the cat 'tabby'; known: stand (taught); zero, sit " \
                                "(description)\n"
    code, _, err = _run(capsys, "pose", "delete", "sit", "--robot", "cat", "--robot-id", "tabby")
    assert code == 1 and "description, not a taught one" in err


def test_play_taught_and_described_poses_in_mujoco(capsys, config_home):
    spec = load_spec("arm")
    reach = np.array([0.6, 0.4, -0.3, 0.2, 0.01])
    save(_pose_file(spec, "a1", reach=reach), poses_path("arm", "a1"))
    code, out, _ = _run(capsys, "pose", "play", "reach", "stand", "--robot", "arm", "--robot-id", "a1",
                        "--durations", "0.8,0.6", "--settle", "0.6", "--json")
    res = json.loads(out)
    assert code == 0 and res["run"]["ok"] and res["run"]["ticks"] == 200
    assert res["controller"]["keyframes"] == ["reach", "stand"] and res["controller"]["durations_s"] == [0.8, 0.6]
    assert res["controller"]["final_error"]["max_abs"] < 0.05  # the arm under gravity, 0.6 s after its last move


# ----------------------------------------------------------------------------- bad input: one line, nothing written
def _arm_file(config_home, name: str = "arm-file.json"):
    path = config_home.parent / name
    save(_pose_file(load_spec("arm"), "a1", reach=np.zeros(5)), path)
    return path


@pytest.mark.parametrize("argv, code, expect", [
    (["play", "nope", "--robot", "cat"], 1, "no pose 'nope' for the cat; known: zero, stand, sit (description)"),
    (["play", "nope", "--robot", "cat", "--robot-id", "tabby"], 1, "known: wave (taught); zero, stand, sit"),
    (["play", "stand", "sit", "zero", "--robot", "cat", "--durations", "1,2"], 1,
     "3 pose(s) need 3 duration(s), the first for the approach from the present pose"),
    (["play", "stand", "--durations", "1,x"], 2, "expected seconds like 2,1.5"),
    (["play", "stand", "sit", "--durations", "1,0.01"], 1, "stand → sit in 0.01 s moves"),
    (["play", "stand", "--port", "/dev/null"], 1, "--port needs --backend dxl"),
    (["list", "--robot", "cat", "--robot-id", "broken"], 1, "broken.poses.json: not valid JSON at line 1 column 24"),
    (["show", "wave", "--robot", "cat", "--robot-id", "partial"], 1, "pose 'wave': no position for hr_roll"),
    (["play", "reach", "--robot", "cat", "--poses", "ARM_FILE"], 1, "holds poses of a 'arm', not of a 'cat'"),
    (["show", "reach", "--robot", "arm", "--robot-id", "a2", "--poses", "ARM_FILE"], 1,
     "holds the poses of arm 'a1', not of 'a2'"),
    (["capture", "stand", "--robot", "cat", "--robot-id", "tabby", "--port", "/dev/null"], 1,
     "'stand' is a pose of the cat's description"),
    (["capture", "hold", "--robot", "cat", "--robot-id", "tabby", "--port", "/dev/null"], 1, "'hold' is taken"),
    (["capture", "wave", "--robot", "cat", "--port", "/dev/null"], 1, "give the robot's id (--robot-id NAME)"),
    (["capture", "wave", "--robot", "cat", "--robot-id", "nocal", "--port", "/dev/null"], 1,
     "no calibration file at"),
    (["delete", "wave", "--robot", "cat"], 1, "give the robot's id"),
], ids=lambda v: " ".join(v[:2]) if isinstance(v, list) else None)
def test_bad_input_is_one_line_and_writes_nothing(capsys, config_home, argv, code, expect):
    spec = load_spec("cat")
    save(_pose_file(spec, "tabby", wave=np.zeros(spec.n)), poses_path("cat", "tabby"))
    poses_path("cat", "broken").write_text("{\"schema\": 1, \"robot\": ")
    partial = _pose_file(spec, "partial", wave=np.zeros(spec.n)).to_dict()
    del partial["poses"]["wave"]["joints"]["hr_roll"]
    poses_path("cat", "partial").write_text(json.dumps(partial))
    arm_file = _arm_file(config_home)
    before = {p: p.read_bytes() for p in config_home.parent.rglob("*") if p.is_file()}
    got, out, err = _run(capsys, "pose", *[str(arm_file) if a == "ARM_FILE" else a for a in argv])
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == code and out == "" and len(lines) == 1 and lines[0].startswith("error: "), err
    assert expect in lines[0], lines[0]
    assert {p: p.read_bytes() for p in config_home.parent.rglob("*") if p.is_file()} == before
