"""``felis replay LOG`` end to end: a run recorded on the virtual bus (the whole hardware path, servos backed by
MuJoCo) replayed in MuJoCo and on the virtual bus again, with the per-joint position error against the
original; and the refusals (another robot's log, a log with no commands, a hardware replay faster than
recorded, a window outside the log), each one line that writes nothing.

The arm sits down (1.3 s of its 1.5 s minimum-jerk move to ``sit``) so every replay has something to follow.
Measured on this (busy, 2-core) machine: joint2 RMS 0.3–0.7° (sim) and 0.3–0.5° (virtual bus), max 1.2–2.1°,
most of it at the start: the replay starts from the pose the servos settle at against gravity, the original
from the model's exact start pose, and the original's wall-clock ticks jitter by milliseconds.
"""

from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from test_cli import felis, ok, tree

from felis.cli.main import main
from felis.cli.replay import check_options, commands_of, robot_of, window
from felis.errors import ParameterError
from felis.hal import State
from felis.logs.reader import read_log
from felis.logs.runlog import RunLog
from felis.spec import load_spec

RMS_BOUND = math.radians(2.0)  # rad, per joint: measured ≤ 0.7° (0.3° on a quiet machine)
MAX_BOUND = math.radians(5.0)  # rad, per joint: measured ≤ 2.1° (1.3° on a quiet machine)


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    """A run of the arm on the virtual bus: ``felis run sit --backend dxl --port virtual --log``."""
    d = tmp_path_factory.mktemp("original")
    # 50 Hz, as the other bus runs of the suite: the machine running the tests may be busy
    ok(felis(d, "run", "sit", "--robot", "arm", "--backend", "dxl", "--port", "virtual", "--duration", "1.3",
             "--rate", "50", "--log", "orig.mcap", "--json", timeout=90))
    return d / "orig.mcap"


def replay(capsys, log, *args) -> dict:
    """``felis replay LOG --json ARGS`` in this process (`felis.cli.main.main`, as the console script runs it: the
    interpreter's start-up is the most of a short replay's time)."""
    rc = main(["replay", str(log), "--json", *args])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


def check_replay(out: dict, path, orig, backend: str) -> dict:
    """The replay's JSON, its log and their agreement; returns the per-joint errors."""
    assert out["run"]["ok"] and out["run"]["controller"] == "replay"
    rep = out["replay"]
    assert rep["backend"] == backend and rep["speed"] == 1.0 and rep["approach_s"] >= 0.5
    assert rep["from_s"] == pytest.approx(orig.cmd_t[0], abs=1e-5)
    assert rep["to_s"] == pytest.approx(orig.cmd_t[-1], abs=1e-5)
    err = rep["position_error"]
    # every tick after the approach replays a logged time in the window: span × rate of them in simulation; on the
    # bus (wall clock) fewer when a busy machine makes ticks overrun (the replay keeps the log's times, not ticks)
    ticks = (rep["to_s"] - rep["from_s"]) * rep["rate_hz"]
    if backend == "sim":
        assert abs(err["samples"] - ticks) <= 2
    else:
        assert 0.5 * ticks <= err["samples"] <= ticks + 2
    assert set(err["joints"]) == {"joint1", "joint2", "joint3", "joint4", "gripper"}
    data = read_log(path)
    assert data.complete and data.summary["replay"] == rep and data.meta["replay"]["of"] == rep["of"]
    assert data.summary["run"]["ticks"] == out["run"]["ticks"] and out["files"]["log"] == str(path)
    # the commands it sent after the approach are the original's (interpolated at the replayed times)
    after = data.cmd_t >= data.cmd_t[0] + rep["approach_s"] + 0.005
    tau = rep["from_s"] + (data.cmd_t[after] - data.cmd_t[0] - rep["approach_s"])
    want = np.stack([np.interp(tau, orig.cmd_t, orig.cmd_q[:, j]) for j in range(5)], -1)
    # log times are whole ns; the bus's ticks are wall-clock, ms off: at the move's peak 1.3 rad/s 0.1 rad is 75 ms
    tol = 1e-6 if backend == "sim" else 0.1
    assert np.abs(data.cmd_q[after] - want).max() < tol
    return err["joints"]


def test_round_trip_sim_and_virtual_bus(tmp_path, original, capsys, monkeypatch):
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "40")  # as `test_cli.felis` gives its subprocesses: a busy machine
    orig = read_log(original)
    assert np.ptp(orig.q[:, 1]) > 0.8  # joint2 swings from upright towards sit (-1.05 rad)
    sim = check_replay(replay(capsys, original, "--backend", "sim", "--log", str(tmp_path / "sim.mcap")),
                       tmp_path / "sim.mcap", orig, "sim")
    bus = check_replay(replay(capsys, original, "--backend", "dxl", "--port", "virtual", "--log",
                              str(tmp_path / "bus.mcap")), tmp_path / "bus.mcap", orig, "dxl")
    with capsys.disabled():
        print()
    for name, errs in (("sim", sim), ("virtual bus", bus)):
        with capsys.disabled():
            print(f"replay on {name}: " + ", ".join(f"{j} RMS {math.degrees(e['rms']):.3f}° max "
                                                     f"{math.degrees(e['max']):.3f}°" for j, e in errs.items()
                                                     if e["unit"] == "rad"))
        for e in errs.values():
            assert e["rms"] is not None and e["rms"] <= RMS_BOUND and e["max"] <= MAX_BOUND, errs
    assert sim["joint2"]["max"] > 0  # the comparison measures something: the arm moved in both runs


def one_line(capsys, rc: int, *fragments: str) -> None:
    """The command (in this process: the same `felis.cli.main.main`) printed one ``error:`` line, exit 1."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 1 and len(lines) == 1 and lines[0].startswith("error: "), err
    for f in fragments:
        assert f in lines[0], lines[0]


def test_another_robots_log_is_one_line(tmp_path, original, capsys):
    one_line(capsys, main(["replay", str(original), "--robot", "cat", "--log", str(tmp_path / "r.mcap")]),
             "a log of robot 'arm', not 'cat'")
    one_line(capsys, main(["replay", str(original), "--backend", "dxl", "--port", "virtual", "--speed", "2"]),
             "--speed 2 on servos", "--backend sim")
    assert tree(tmp_path) == set()
    assert not list(original.parent.glob("*-replay-*"))  # nothing beside the original either


def test_refusals_before_anything_opens(tmp_path, original, capsys):
    data = read_log(original)
    arm = load_spec("arm")
    assert robot_of(data, None).name == "arm" and robot_of(data, "arm").name == "arm"
    other = dataclasses.replace(data, joints=["joint1", "joint2", "joint3", "gripper", "joint4"])
    with pytest.raises(ParameterError, match="joints .* are not arm's"):
        robot_of(other, None)
    cmds = commands_of(data)
    assert window(cmds, None, None) == (cmds.t[0], cmds.t[-1])
    assert window(cmds, 0.5, 1.0) == (0.5, 1.0)
    for a, b, what in ((0.5, 0.4, "before --to"), (5.0, None, "--from 5"), (None, 9.0, "--to 9")):
        with pytest.raises(ParameterError, match=what):
            window(cmds, a, b)

    def opts(**kw):
        base = dict(port=None, robot_id=None, calibration=None, imu_port=None, speed=1.0, approach=None, log=None,
                    file=original)
        return SimpleNamespace(**{**base, **kw})

    assert check_options(opts(), "sim") == original.with_name("orig-replay-sim.mcap")
    for kw, backend, what in (({"speed": 0.0}, "sim", "--speed must be"), ({"speed": 1.5}, "dxl", "on servos"),
                              ({"port": "virtual"}, "sim", "--port needs"), ({"log": original}, "sim", "overwrite"),
                              ({"log": tmp_path / "r.txt"}, "sim", ".mcap"), ({"approach": -1.0}, "sim", "--approach")):
        with pytest.raises(ParameterError, match=what):
            check_options(opts(**kw), backend)

    # a log with measured states and no sent commands: nothing to replay, one line through the command
    with RunLog(tmp_path / "states.mcap", arm, {"kind": "monitor"}) as log:
        for k in range(5):
            log.state(State(t=0.01 * k, q=np.zeros(arm.n), dq=np.zeros(arm.n)))
        log.close()
    with pytest.raises(ParameterError, match="no sent commands .*monitor"):
        commands_of(read_log(tmp_path / "states.mcap"))
    one_line(capsys, main(["replay", str(tmp_path / "states.mcap")]), "no sent commands")
    assert tree(tmp_path) == {"states.mcap"}

