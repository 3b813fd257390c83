"""Calibration end to end: motor set-up, joint calibration, files, diff/apply, EEPROM settings.

Real parts throughout: the unmodified dynamixel-sdk over a pseudo-terminal against the virtual bus,
real files in a temporary config directory; the operator's hands are a `ScriptedOperator` (API) or
a test thread answering the command's prompts on its standard input (CLI).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from felis.calib import calfile
from felis.calib.calfile import CalibrationFile, JointCalibration, calibration_path, load, save, zero_tick
from felis.calib.eeprom import SHUTDOWN_MASK, apply, apply_calibration, check_settings, diff_calibration
from felis.calib.joints import calibrate
from felis.calib.operator import ScriptedOperator
from felis.calib.setup import setup_motors
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.robot import DynamixelRobot
from felis.drivers.virtual import Mount, VirtualBus, VirtualServo
from felis.errors import CalibrationError
from felis.servos import RAD_PER_TICK
from felis.spec import load_spec

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def config_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    # the virtual bus serves from this (busy) test process: allow its thread a scheduling hiccup
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "40")
    return tmp_path / "config"


def _offsets(spec, seed=1, span_deg=40.0):
    rng = np.random.default_rng(seed)
    return {j.name: math.radians(float(rng.uniform(-span_deg, span_deg))) for j in spec.joints}


class Hands:
    """What the operator's hands do to a virtual robot: pose it, sweep it."""

    def __init__(self, vbus: VirtualBus, spec, sweep_q: dict[str, tuple[float, float]] | None = None, steps=12):
        self.vbus, self.spec, self.steps = vbus, spec, steps
        # the arm's base turns ±π: a whole turn, whose ends are the same tick; hands stop a little short
        self.sweep_q = sweep_q or {j.name: (max(j.lower, -3.1), min(j.upper, 3.1)) for j in spec.joints}

    def pose(self, q: dict[str, float] | None = None) -> None:
        q = q or {}
        with self.vbus.lock:
            for j in self.spec.joints:
                s = self.vbus.servo(j.servo_id)
                s.angle = s.mount.horn(q.get(j.name, 0.0))

    def on_wait(self, message: str) -> None:
        if "reference pose" in message:
            self.pose()

    def on_sweep(self, k: int) -> bool:
        if k > self.steps:
            self.pose()
            return True
        f = k / self.steps
        self.pose({n: lo + (hi - lo) * f for n, (lo, hi) in self.sweep_q.items()})
        return False


def _robot_bus(name="cat", seed=1, span=40.0, **kw):
    spec = load_spec(name)
    vb = VirtualBus.for_robot(spec, mount_offsets=_offsets(spec, seed, span), **kw)
    return spec, vb


def _scramble(vb, spec, seed=5):
    rng = np.random.default_rng(seed)
    Hands(vb, spec).pose({j.name: float(rng.uniform(j.lower, j.upper)) * 0.5 for j in spec.joints})


# ----------------------------------------------------------------------------- files
def _cal(spec, robot_id="tabby", offset=0) -> CalibrationFile:
    joints = {j.name: JointCalibration(j.servo_id, j.servo, 52, offset, j.direction, calfile.description_ticks(j))
              for j in spec.joints}
    return CalibrationFile(robot=spec.name, robot_id=robot_id, joints=joints)


def test_file_round_trip_backup_and_xdg_location(config_home):
    spec = load_spec("cat")
    path = calibration_path("cat", "tabby")
    assert path == config_home / "felis" / "calibration" / "cat" / "tabby.json"
    save(_cal(spec, offset=5), path)
    save(_cal(spec, offset=7), path)
    assert load(path, spec).joints["fl_pitch"].offset == 7
    assert load(calfile.backup_path(path), spec).joints["fl_pitch"].offset == 5
    data = json.loads(path.read_text())
    assert data["schema"] == 1 and data["robot"] == "cat" and data["robot_id"] == "tabby" and data["created"]
    assert set(data["joints"]["spine_pitch"]) == {"id", "model", "firmware", "offset", "direction", "range"}


@pytest.mark.parametrize("text, expect", [
    ("", "empty"),
    ('{"schema": 1, "robot": "cat", "robot_id": "tabby", "created": "x", "joints": {"spine_pitch": {"id": 1',
     "not valid JSON"),
    ('{"schema": 1, "robot": "cat", "robot_id": "tabby", "created": "x"}', "joints: missing"),
    ('{"schema": 9, "robot": "cat", "robot_id": "tabby", "created": "x", "joints": {}}', "schema 9"),
])
def test_corrupt_file_is_one_clear_line_naming_the_backup(text, expect):
    spec = load_spec("cat")
    path = calibration_path("cat", "tabby")
    save(_cal(spec, offset=3), path)
    save(_cal(spec, offset=4), path)
    path.write_text(text)
    with pytest.raises(CalibrationError, match=expect) as e:
        load(path, spec)
    assert "\n" not in str(e.value) and "tabby.json.bak" in str(e.value)
    assert load(calfile.backup_path(path), spec).joints["fl_pitch"].offset == 3


def test_partial_file_names_the_missing_joints():
    spec = load_spec("cat")
    cal = _cal(spec)
    partial = CalibrationFile("cat", "tabby", {k: v for k, v in cal.joints.items() if k != "hr_roll"})
    path = save(partial, calibration_path("cat", "tabby"))
    with pytest.raises(CalibrationError, match="partial: no calibration for hr_roll"):
        load(path, spec)


def test_write_killed_between_writing_and_renaming_loses_nothing(tmp_path):
    spec = load_spec("cat")
    path = tmp_path / "tabby.json"
    save(_cal(spec, offset=11), path)
    before = path.read_bytes()
    script = textwrap.dedent(f"""
        import os, signal
        from felis.calib import calfile
        from felis.spec import load_spec
        from felis.calib.calfile import CalibrationFile, JointCalibration
        spec = load_spec("cat")
        joints = {{j.name: JointCalibration(j.servo_id, j.servo, 52, 99, j.direction, calfile.description_ticks(j))
                  for j in spec.joints}}
        real = os.replace
        def killing_replace(src, dst):
            if str(dst) == {str(path)!r}:
                os.kill(os.getpid(), signal.SIGKILL)  # the new text is written and synced; the rename never happens
            return real(src, dst)
        os.replace = killing_replace
        calfile.save(CalibrationFile("cat", "tabby", joints), {str(path)!r})
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    assert path.read_bytes() == before
    assert load(path, spec).joints["fl_pitch"].offset == 11
    assert list(tmp_path.glob(".tabby.json.*.tmp")), "the killed write's temporary file is left beside, not over"


@pytest.mark.parametrize("bad", ["../evil", "a/b", "", " tabby", "x" * 65, ".hidden", "a..b"])
def test_robot_id_with_path_characters_is_refused(bad):
    with pytest.raises(CalibrationError, match="cannot name a calibration file"):
        calibration_path("cat", bad)


# ----------------------------------------------------------------------------- motor set-up
def _factory_chain(spec):
    """One factory-new servo per joint (all ID 1 at 57600), none plugged in yet."""
    servos = [VirtualServo(j.servo, 1, 57_600) for j in spec.joints]
    vb = VirtualBus(servos)
    for s in servos:
        vb.remove_servo(s)
    return vb, servos


def test_setup_motors_renumbers_a_chain_of_factory_servos_and_is_idempotent():
    spec = load_spec("arm")
    vb, servos = _factory_chain(spec)
    with vb, DynamixelBus(vb.port, 57_600) as bus:
        plugged = []

        def plug_next(message):
            for s in plugged:
                vb.remove_servo(s)  # "connect ONLY the servo of …"
            s = servos[len(plugged)]
            vb.restore_servo(s)
            plugged.append(s)

        op = ScriptedOperator(on_wait=plug_next)
        done = setup_motors(bus, spec, op, baud=1_000_000)
        assert [d.changed for d in done] == [[f"ID 1 → {j.servo_id}", "baud 57600 → 1000000"] for j in spec.joints]
        assert [(s.id, s.baud_bps) for s in servos] == [(j.servo_id, 1_000_000) for j in spec.joints]
        for s in servos:  # the whole chain, now all plugged in together
            vb.restore_servo(s)
        assert sorted(f.id for f in bus.scan(bauds=[1_000_000])) == [j.servo_id for j in spec.joints]
        # again, a subset: nothing to change, and the rest untouched
        for s in servos:
            vb.remove_servo(s)
        vb.restore_servo(servos[2])
        again = setup_motors(bus, spec, ScriptedOperator(), joints=["joint3"], baud=1_000_000)
        assert again[0].changed == [] and again[0].found_id == 13


def test_setup_refuses_two_servos_on_one_id_a_missing_servo_and_the_wrong_model():
    spec = load_spec("arm")
    a, b = VirtualServo("XM430-W350-T", 1, 57_600), VirtualServo("XM430-W350-T", 1, 57_600)
    with VirtualBus([a, b]) as vb, DynamixelBus(vb.port, 57_600) as bus:
        with pytest.raises(CalibrationError, match="two servos share ID 1"):
            setup_motors(bus, spec, ScriptedOperator(), joints=["joint1"])
        assert (a.id, b.id) == (1, 1)  # nothing written
        vb.remove_servo(a)
        vb.remove_servo(b)
        t = time.monotonic()
        with pytest.raises(CalibrationError, match="no servo answers"):
            setup_motors(bus, spec, ScriptedOperator(), joints=["joint1"])
        assert time.monotonic() - t < 30
        vb.add_servo(VirtualServo("XL330-M288-T", 1, 57_600))
        with pytest.raises(CalibrationError, match="needs a XM430-W350-T.*is a XL330-M288-T"):
            setup_motors(bus, spec, ScriptedOperator(), joints=["joint1"])


# ----------------------------------------------------------------------------- joint calibration
def test_calibration_zeros_match_the_simulated_zero_within_one_tick():
    spec, vb = _robot_bus("cat", seed=3)
    _scramble(vb, spec)
    hands = Hands(vb, spec)
    with vb:
        with DynamixelBus(vb.port, 1_000_000) as bus:
            cal, path = calibrate(bus, spec, "tabby", ScriptedOperator(hands.on_wait, hands.on_sweep))
        assert path == calibration_path("cat", "tabby") and load(path, spec) == cal
        for j in spec.joints:
            jc = cal.joints[j.name]
            assert abs(vb.servo(j.servo_id).get("present_position") - zero_tick(j)) <= 1
            lo, hi = calfile.description_ticks(j)
            assert abs(jc.range[0] - lo) <= 2 and abs(jc.range[1] - hi) <= 2
            assert vb.servo(j.servo_id).get("min_position_limit") == jc.range[0]
        # the calibrated robot reads the simulated joint positions, whatever the horn mounting
        rng = np.random.default_rng(7)
        q = {j.name: float(rng.uniform(j.lower, j.upper)) for j in spec.joints}
        hands.pose(q)
        with DynamixelRobot(spec, vb.port, calibration=cal.for_robot(spec)) as robot:
            got = robot.read().q
    want = np.array([q[n] for n in spec.names])
    assert np.max(np.abs(got - want) / RAD_PER_TICK) <= 1.0


def test_calibrating_a_subset_keeps_the_rest_and_needs_a_file():
    spec, vb = _robot_bus("arm", seed=4)
    hands = Hands(vb, spec)
    with vb, DynamixelBus(vb.port, 1_000_000) as bus:
        with pytest.raises(CalibrationError, match="needs a complete file"):
            calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep), joints=["joint2"])
        first, path = calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep))
        vb.servo(12).mount = Mount(1, 0.0, 1.0, math.radians(12))  # joint2's horn remounted 12° off
        hands.pose()
        second, _ = calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep), joints=["joint2"])
    assert second.joints["joint1"] == first.joints["joint1"]
    assert second.joints["joint2"].offset != first.joints["joint2"].offset
    assert load(calfile.backup_path(path), spec) == first


def test_calibration_knows_the_operating_mode():
    """A servo in another mode than its joint's is refused before anything is written; an extended-position joint
    (mode 4) that has turned twice since power-up is rebooted so that it counts from one turn, as it will after
    the next power cycle, and calibrates to its zero."""
    from dataclasses import replace

    arm = load_spec("arm")
    spec = replace(arm, joints=tuple(replace(j, operating_mode=4) if j.name == "joint4" else j for j in arm.joints))
    vb = VirtualBus.for_robot(spec, mount_offsets=_offsets(spec, 6, 30.0))
    hands = Hands(vb, spec)
    wrist = vb.servo(spec.joints[spec.names.index("joint4")].servo_id)
    def pose_after_two_turns(message):
        hands.on_wait(message)
        wrist.angle = wrist.angle + 4 * math.pi  # the same horn angle, two turns on the servo's count

    with vb:
        with DynamixelBus(vb.port, 1_000_000) as bus:
            gripper = vb.servo(spec.joints[spec.names.index("gripper")].servo_id)
            gripper.set("operating_mode", 3)
            with pytest.raises(CalibrationError, match=r"gripper \(ID 15\) runs mode 3, the description says 5"):
                calibrate(bus, spec, "arm4", ScriptedOperator(hands.on_wait, hands.on_sweep))
            gripper.set("operating_mode", 5)
            assert all(s.get("homing_offset") == 0 for s in vb.servos)
            op = ScriptedOperator(pose_after_two_turns, hands.on_sweep)
            cal, _ = calibrate(bus, spec, "arm4", op)
        hands.pose()
        assert any("rebooted joint4" in m for m in op.log), op.log
        assert abs(wrist.get("present_position") - zero_tick(spec.joints[3])) <= 1
        with DynamixelRobot(spec, vb.port, calibration=cal.for_robot(spec)) as robot:
            assert np.max(np.abs(robot.read().q) / RAD_PER_TICK) <= 1.0


@pytest.mark.parametrize("case, expect", [
    ("overflow", "Homing Offset holds at most ±90°"),
    ("unswept", "was not swept"),
    ("seam", "0/4095 seam"),
    ("unreachable", "goes past what the joint can reach"),
])
def test_bad_calibrations_are_refused_with_nothing_half_written(case, expect):
    spec = load_spec("arm")
    offsets = _offsets(spec, 2, 30.0)
    sweep = {j.name: (max(j.lower, -3.1), min(j.upper, 3.1)) for j in spec.joints}
    if case == "overflow":
        offsets["joint3"] = math.radians(100)
    elif case == "unswept":
        sweep["joint2"] = (0.0, 0.0)
    elif case == "seam":
        sweep["joint1"] = (-math.pi - 0.2, math.pi + 0.2)
    else:
        sweep["joint4"] = (-1.7, 2.6)
    vb = VirtualBus.for_robot(spec, mount_offsets=offsets)
    hands = Hands(vb, spec, sweep)
    path = calibration_path("arm", "bad")
    with vb, DynamixelBus(vb.port, 1_000_000) as bus:
        before = {s.id: bytes(s.mem[48:56]) for s in vb.servos}
        with pytest.raises(CalibrationError, match=expect) as e:
            calibrate(bus, spec, "bad", ScriptedOperator(hands.on_wait, hands.on_sweep))
        assert "\n" not in str(e.value)
        assert {s.id: bytes(s.mem[48:56]) for s in vb.servos} == before  # position limits untouched
        assert all(s.get("homing_offset") == 0 for s in vb.servos)  # offsets untouched, or put back
    assert not path.exists()


def test_missing_servo_is_named():
    spec, vb = _robot_bus("arm")
    vb.remove_servo(13)
    with vb, DynamixelBus(vb.port, 1_000_000) as bus:
        with pytest.raises(CalibrationError, match=r"no reply from joint3 \(ID 13\)"):
            calibrate(bus, spec, "arm1", ScriptedOperator())
    assert not calibration_path("arm", "arm1").exists()


# ----------------------------------------------------------------------------- diff / apply
def test_diff_and_apply_both_ways():
    spec, vb = _robot_bus("arm", seed=6)
    hands = Hands(vb, spec)
    with vb, DynamixelBus(vb.port, 1_000_000) as bus:
        cal, path = calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep))
        assert diff_calibration(bus, spec, cal) == []
        # someone changed joint2 by hand: the file wins
        bus.write(12, "homing_offset", cal.joints["joint2"].offset + 40, raw=True)
        diffs = diff_calibration(bus, spec, cal)
        assert [(d.joint, d.item, d.motor, d.expected) for d in diffs] == [
            ("joint2", "homing_offset", cal.joints["joint2"].offset + 40, cal.joints["joint2"].offset)]
        apply_calibration(bus, spec, cal, "file", path)
        assert diff_calibration(bus, spec, cal) == [] and vb.servo(12).get("homing_offset") == cal.joints[
            "joint2"].offset
        # the motors were re-done on purpose: the motors win, the file is rewritten, the old one kept
        bus.write(14, "max_position_limit", cal.joints["joint4"].range[1] - 30, raw=True)
        _, new = apply_calibration(bus, spec, cal, "motors", path)
        assert new.joints["joint4"].range[1] == cal.joints["joint4"].range[1] - 30
        assert load(path, spec) == new and load(calfile.backup_path(path), spec) == cal
        assert diff_calibration(bus, spec, new) == []
        # motors that do not hold a valid calibration cannot win
        bus.write(13, "min_position_limit", 2040, raw=True)
        bus.write(13, "max_position_limit", 2050, raw=True)
        with pytest.raises(CalibrationError, match="do not hold a valid calibration.*not swept"):
            apply_calibration(bus, spec, new, "motors", path)
        assert load(path, spec) == new


def test_connect_refuses_motors_that_disagree_with_the_file():
    spec, vb = _robot_bus("arm", seed=8)
    hands = Hands(vb, spec)
    with vb:
        with DynamixelBus(vb.port, 1_000_000) as bus:
            cal, _ = calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep))
            bus.write(11, "homing_offset", 0, raw=True)
        robot = DynamixelRobot(spec, vb.port, calibration=cal.for_robot(spec))
        with pytest.raises(CalibrationError, match=r"joint1 \(ID 11\) holds 0"):
            robot.connect()
        robot.close()


# ----------------------------------------------------------------------------- EEPROM settings
def test_eeprom_settings_check_and_apply():
    spec = load_spec("arm")
    servos = [VirtualServo(j.servo, j.servo_id, 1_000_000) for j in spec.joints]  # factory settings otherwise
    with VirtualBus(servos) as vb, DynamixelBus(vb.port, 1_000_000) as bus:
        vb.servo(12).set("operating_mode", 4)
        vb.servo(13).set("shutdown", 0)
        diffs = check_settings(bus, spec)
        items = {(d.servo_id, d.item) for d in diffs}
        assert {(i, "return_delay_time") for i in range(11, 16)} <= items
        assert (12, "operating_mode") in items and (13, "shutdown") in items
        assert (11, "min_position_limit") not in items  # joint1 spans the whole turn: factory 0…4095
        assert (12, "min_position_limit") in items
        apply(bus, spec, diffs)
        assert check_settings(bus, spec) == []
        assert vb.servo(13).get("shutdown") == SHUTDOWN_MASK and vb.servo(12).get("operating_mode") == 3
        # baud: the servos move to the robot's rate and the bus follows
        diffs = check_settings(bus, spec, baud=2_000_000)
        assert {d.item for d in diffs} == {"baud_rate"}
        apply(bus, spec, diffs)
        assert bus.baud == 2_000_000 and all(s.baud_bps == 2_000_000 for s in servos)


# ----------------------------------------------------------------------------- the commands
def _felis(*args, env=None, **kw):
    e = dict(os.environ, **(env or {}))
    return subprocess.Popen([sys.executable, "-m", "felis", *args], cwd=ROOT, env=e, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw)


def _answer(proc, actions: dict[str, callable], timeout=60.0) -> list[str]:
    """Read the command's output; when a line contains a key, run its action and press Enter."""
    lines: list[str] = []
    deadline = time.monotonic() + timeout

    def pump():
        for line in proc.stdout:
            lines.append(line)
            for key, act in list(actions.items()):
                if key in line:
                    act()
                    try:
                        proc.stdin.write("\n")
                        proc.stdin.flush()
                    except BrokenPipeError:  # the command ended (its error is in the test's assertion)
                        return
    t = threading.Thread(target=pump, daemon=True)
    t.start()
    proc.wait(timeout=max(1.0, deadline - time.monotonic()))
    t.join(5)
    return lines


def test_cli_calibrate_show_diff_apply_with_an_operator_at_the_keyboard(config_home):
    spec, vb = _robot_bus("arm", seed=9)
    hands = Hands(vb, spec, steps=6)
    env = {"XDG_CONFIG_HOME": str(config_home)}
    with vb:
        def sweep():
            for k in range(hands.steps + 2):
                hands.on_sweep(k)
                time.sleep(0.12)

        proc = _felis("calibrate", "--robot", "arm", "--id", "bench-1", "--port", vb.port, env=env)
        out = _answer(proc, {"reference pose": hands.pose, "through its whole": sweep})
        assert proc.returncode == 0, "".join(out) + proc.stderr.read()
        path = calibration_path("arm", "bench-1")
        cal = load(path, spec)
        for j in spec.joints:
            assert abs(vb.servo(j.servo_id).get("present_position") - zero_tick(j)) <= 1
        show = subprocess.run([sys.executable, "-m", "felis", "calibration", "show", "--robot", "arm", "--id",
                               "bench-1", "--json"], cwd=ROOT, env=dict(os.environ, **env), capture_output=True,
                              text=True)
        assert json.loads(show.stdout)["joints"]["joint2"]["offset"] == cal.joints["joint2"].offset
        with DynamixelBus(vb.port, 1_000_000) as bus:
            bus.write(11, "homing_offset", cal.joints["joint1"].offset + 3, raw=True)
        diff = subprocess.run([sys.executable, "-m", "felis", "calibration", "diff", "--robot", "arm", "--id",
                               "bench-1", "--port", vb.port, "--json"], cwd=ROOT, env=dict(os.environ, **env),
                              capture_output=True, text=True)
        d = json.loads(diff.stdout)
        assert d["same"] is False and d["differences"][0]["item"] == "homing_offset"
        ap = subprocess.run([sys.executable, "-m", "felis", "calibration", "apply", "--robot", "arm", "--id",
                             "bench-1", "--port", vb.port, "--prefer", "file", "--yes", "--json"], cwd=ROOT,
                            env=dict(os.environ, **env), capture_output=True, text=True)
        assert ap.returncode == 0, ap.stderr
        assert vb.servo(11).get("homing_offset") == cal.joints["joint1"].offset


@pytest.mark.parametrize("argv, expect", [
    (["calibrate", "--robot", "arm", "--id", "../x", "--port", "/dev/null"], "cannot name a calibration file"),
    (["calibration", "show", "--robot", "arm", "--id", "nobody"], "no calibration file at"),
    (["calibrate", "--robot", "arm", "--id", "a1", "--joints", "elbow", "--port", "/dev/null"], "no joint 'elbow'"),
])
def test_cli_bad_input_is_one_line(argv, expect, config_home):
    p = subprocess.run([sys.executable, "-m", "felis", *argv], cwd=ROOT, capture_output=True, text=True,
                       env=dict(os.environ, XDG_CONFIG_HOME=str(config_home)), timeout=60)
    assert p.returncode != 0
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and expect in lines[0], p.stderr


def test_cli_setup_motors_prompts_for_each_servo_in_turn(config_home):
    spec = load_spec("arm")
    vb, servos = _factory_chain(spec)
    with vb:
        plugged = []

        def plug_next():
            for s in plugged:
                vb.remove_servo(s)
            plugged.append(servos[len(plugged)])
            vb.restore_servo(plugged[-1])

        proc = _felis("setup-motors", "--robot", "arm", "--motors", "joint1,joint2", "--port", vb.port)
        out = _answer(proc, {"connect ONLY": plug_next})
        assert proc.returncode == 0, "".join(out) + proc.stderr.read()
    assert [(s.id, s.baud_bps) for s in servos[:2]] == [(11, 1_000_000), (12, 1_000_000)]
    assert [(s.id, s.baud_bps) for s in servos[2:]] == [(1, 57_600)] * 3  # not asked for: untouched


def test_run_checks_eeprom_settings_when_the_robot_connects(config_home):
    spec, vb = _robot_bus("arm", seed=10, span=0.0)
    hands = Hands(vb, spec)
    env = dict(os.environ, XDG_CONFIG_HOME=str(config_home))
    with vb:
        with DynamixelBus(vb.port, 1_000_000) as bus:
            calibrate(bus, spec, "arm1", ScriptedOperator(hands.on_wait, hands.on_sweep))
        vb.servo(13).set("return_delay_time", 250)  # as from the factory
        argv = [sys.executable, "-m", "felis", "run", "hold", "--robot", "arm", "--backend", "dxl", "--port", vb.port,
                "--robot-id", "arm1", "--duration", "0.3", "--json"]
        refused = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, stdin=subprocess.DEVNULL)
        assert refused.returncode != 0 and "no answer on standard input" in refused.stderr
        assert vb.servo(13).get("return_delay_time") == 250
        ok = subprocess.run([*argv, "--yes"], cwd=ROOT, env=env, capture_output=True, text=True)
        assert ok.returncode == 0, ok.stderr
        assert "joint3.return_delay_time 250→0" in " ".join(json.loads(ok.stdout)["warnings"])
        assert vb.servo(13).get("return_delay_time") == 0


def test_cli_imu_mounting_goes_into_the_calibration_file(config_home):
    from felis.drivers.virtual import spawn
    from felis.rotations import quat_from_ypr

    mount = quat_from_ypr(0.0, math.radians(-4.0), math.radians(6.0))  # sensor pitched −4°, rolled 6°
    env = dict(os.environ, XDG_CONFIG_HOME=str(config_home))
    with spawn("cat", sim=True, imu_mount=mount) as vb:
        p = subprocess.run([sys.executable, "-m", "felis", "calibrate", "--robot", "cat", "--id", "t1", "--port",
                            vb.port, "--imu", "--imu-port", vb.imu_port, "--no-sweep", "--yes", "--json"],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    cal = load(calibration_path("cat", "t1"), load_spec("cat"))
    rot = np.asarray(cal.imu["rotation"])
    assert abs(abs(float(np.dot(rot, mount))) - 1.0) < 1e-4  # within ≈ 1.6° (in practice 0.03°)
    assert cal.for_robot(load_spec("cat")).imu_rotation is not None


@pytest.mark.parametrize("content, expect", [
    ('{"schema": 1, "robot": "cat", "robot_id": "tabby", "created": "x", "joints": {"spine_', "not valid JSON"),
    ("partial", "partial: no calibration for hr_roll"),
    ("unreachable", "goes past what the joint can reach"),
])
def test_importing_a_bad_file_leaves_the_current_calibration_intact(tmp_path, config_home, content, expect):
    spec = load_spec("cat")
    current = save(_cal(spec, offset=21), calibration_path("cat", "tabby"))
    before = current.read_bytes()
    src = tmp_path / "in.json"
    data = _cal(spec).to_dict()
    if content == "partial":
        del data["joints"]["hr_roll"]
        content = json.dumps(data)
    elif content == "unreachable":
        data["joints"]["spine_yaw"]["range"] = [1000, 3900]  # ±60° joint: 3900 ticks is +163°
        content = json.dumps(data)
    src.write_text(content)
    p = subprocess.run([sys.executable, "-m", "felis", "calibration", "import", str(src), "--yes"], cwd=ROOT,
                       env=dict(os.environ, XDG_CONFIG_HOME=str(config_home)), capture_output=True, text=True)
    assert p.returncode != 0 and len(p.stderr.strip().splitlines()) == 1 and expect in p.stderr, p.stderr
    assert current.read_bytes() == before


def test_calibration_against_the_mujoco_model_reads_its_joint_angles_within_one_tick():
    """Servo-in-the-loop: the horns are MuJoCo joints mounted off their marks; after calibration the
    robot's q equals the model's qpos for any pose, to one encoder tick."""
    spec = load_spec("cat")
    from felis.sim.servo_in_loop import virtual_bus

    vb = virtual_bus(spec, sim=True, mount_offsets=_offsets(spec, seed=12, span_deg=45.0))
    lo = np.array([j.lower for j in spec.joints])
    hi = np.array([j.upper for j in spec.joints])

    def on_wait(message):
        vb.backend.pose(np.zeros(spec.n))  # the operator holds the cat in the reference pose

    def on_sweep(k):
        if k > 8:
            vb.backend.pose(np.zeros(spec.n))
            return True
        vb.backend.pose(lo + (hi - lo) * k / 8)
        return False

    with vb:
        with DynamixelBus(vb.port, 1_000_000) as bus:
            cal, _ = calibrate(bus, spec, "sim-cat", ScriptedOperator(on_wait, on_sweep))
        rng = np.random.default_rng(3)
        q = rng.uniform(lo, hi) * 0.9
        vb.backend.pose(q)
        model_q = vb.backend.robot.data.qpos[vb.backend.robot._qadr].copy()
        with DynamixelRobot(spec, vb.port, calibration=cal.for_robot(spec)) as robot:
            got = robot.read().q
    assert np.max(np.abs(got - model_q)) / RAD_PER_TICK <= 1.0
