"""Gait data for phase learning: the stepping controller's schedule, recordings of the MuJoCo cat, step
frequency from foot contacts, run logs (made by the ``felis`` command through the virtual bus), files,
and ``felis phase record``. Real MuJoCo, real logs and files, no mocks."""

from __future__ import annotations

import dataclasses
import json
import math
import random

import numpy as np
import pytest
from test_cli import felis, ok

from felis.controllers.stepping import BLEND_S, SteppingController
from felis.errors import ParameterError, PhaseError
from felis.hal import State
from felis.learning.phase.data import (
    HELDOUT,
    TRAIN,
    GaitRecording,
    contact_frequency,
    from_log,
    load_recordings,
    record_sim,
    save_recordings,
    schedule_seconds,
)
from felis.logs.runlog import RunLog
from felis.spec import load_spec

# stand, trot at 2 Hz, change to 2.5 Hz, stand: the gait starts at BLEND_S, segments at 0.3/1.3/6.3/11.3 s
TROT = ((1.0, 0.0, 0.0), (5.0, 2.0, 0.5), (5.0, 2.5, 0.5), (1.5, 0.0, 0.0))


def _state(spec, t):
    return State(t=t, q=spec.pose("stand"), dq=np.zeros(spec.n))


def _one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text and "Traceback" not in text
    return text


def fields(g) -> tuple:
    return tuple(v.tolist() if isinstance(v, np.ndarray) else v for v in dataclasses.astuple(g))


# ------------------------------------------------------------------------------------------ the schedule


def test_schedule_phase_is_continuous_through_a_frequency_change_and_gait_is_pure():
    spec = load_spec("cat")
    c = SteppingController.scheduled([(1.0, 0.0, 0.0), (2.0, 2.0, 0.5), (2.0, 2.5, 0.35), (1.0, 0.0, 0.0)])
    c.reset(spec, _state(spec, 0.0))
    t_s = BLEND_S
    assert c.end_s == pytest.approx(t_s + 6.0)
    ts = np.arange(0.0, 8.0, 0.001)
    gaits = [c.gait(t) for t in ts]
    phase = np.unwrap(np.array([g.phase for g in gaits]) * 2 * np.pi) / (2 * np.pi)
    freq = np.array([g.frequency_hz for g in gaits])
    # the phase integrates the frequency: no jump anywhere, f·dt per step (a change inside a step: Δf·dt at most)
    assert np.abs(np.diff(phase) - freq[:-1] * 0.001).max() <= 0.5 * 0.001 + 1e-9
    change = t_s + 3.0
    for t in (t_s + 1.0, change, t_s + 5.0):  # every boundary, on the circle
        assert abs((c.gait(t - 1e-9).phase - c.gait(t).phase + 0.5) % 1.0 - 0.5) < 1e-8
    assert phase[-1] - phase[0] == pytest.approx(2.0 * 2.0 + 2.5 * (ts[-1] - change), abs=1e-6)
    assert c.gait(change - 0.01).frequency_hz == 2.0 and c.gait(change + 0.01).frequency_hz == 2.5
    # stand → trot: the lift ramps up from 0; trot → trot: the ramp level stays 1, the lift ramps linearly
    assert not c.gait(t_s + 0.5).stepping and c.gait(t_s + 1.25).lift == pytest.approx(0.25)
    assert c.gait(change + 0.25).amplitude == 1.0 and c.gait(change + 0.25).lift == pytest.approx(0.425)
    assert c.gait(change + 0.6).lift == 0.35
    # trot → stand: lift and ramp level down to 0 over ramp_s, then exactly the standing controller's pose
    end = t_s + 5.0
    assert 0 < c.gait(end + 0.25).lift == pytest.approx(0.175) and c.gait(end + 0.25).amplitude == 0.5
    assert not c.gait(end + 0.5).stepping and c.gait(end + 0.5).lift == 0.0
    still = SteppingController(lift=0.0)
    still.reset(spec, _state(spec, 0.0))
    for t in (0.5, end + 0.5 - 0.04, end + 1.0, 20.0):  # the command runs 40 ms ahead of the clock
        assert np.array_equal(c(_state(spec, t)).q, still(_state(spec, t)).q)
    assert not np.array_equal(c(_state(spec, end + 0.2)).q, still(_state(spec, end + 0.2)).q)
    # a pure function of t: any order, any number of calls, the same gait
    order = list(range(0, len(ts), 37))
    random.Random(0).shuffle(order)
    for k in order:
        assert fields(c.gait(ts[k])) == fields(gaits[k]) == fields(c.gait(ts[k]))


@pytest.mark.parametrize("f, lift, ramp_s, start_s", [(2.0, 0.5, 0.5, 0.0), (1.5, 0.35, 1.0, 1.0),
                                                      (2.5, 0.65, 0.0, 0.2), (0.0, 0.5, 0.5, 0.0),
                                                      (2.0, 0.0, 0.5, 0.0)])
def test_a_constant_schedule_is_the_plain_controller_bit_for_bit(f, lift, ramp_s, start_s):
    spec = load_spec("cat")
    plain = SteppingController(frequency_hz=f, lift=lift, ramp_s=ramp_s, start_s=start_s)
    sched = SteppingController.scheduled([(4.0, f, lift)], ramp_s=ramp_s, start_s=start_s)
    start = State(t=1.0, q=spec.pose("sit"), dq=np.zeros(spec.n))
    plain.reset(spec, start)
    sched.reset(spec, start)
    for t in np.arange(0.0, 9.0, 0.01):  # past the segment's end: the last segment holds
        assert fields(plain.gait(t)) == fields(sched.gait(t))
        assert np.array_equal(plain(_state(spec, t)).q, sched(_state(spec, t)).q)


@pytest.mark.parametrize("segments, match", [
    ([], "empty"), (None, "sequence"), ([(1.0, 2.0)], "segment 0"), (["abc"], "segment 0"),
    ([(1.0, 2.0, 0.5), (0.0, 2.0, 0.5)], "segment 1: duration_s"), ([(-1.0, 2.0, 0.5)], "duration_s"),
    ([(1.0, 4.5, 0.5)], "frequency"), ([(1.0, -1.0, 0.5)], "frequency"), ([(1.0, 2.0, 0.9)], "lift"),
    ([(1.0, float("nan"), 0.5)], "finite"), ([(float("inf"), 2.0, 0.5)], "finite"), ([(1.0, "x", 0.5)], "finite"),
])
def test_bad_schedules(segments, match):
    with pytest.raises(ParameterError, match=match) as err:
        SteppingController.scheduled(segments)
    _one_line(err)


# ------------------------------------------------------------------------------------------ recordings


@pytest.fixture(scope="module")
def trot() -> GaitRecording:
    return record_sim(TROT, name="trot")


def test_recording_fields(trot):
    r = trot
    n = len(r.t)
    assert n == round((BLEND_S + 12.5) * 100) and r.q.shape == (n, 12) and r.contacts.shape == (n, 4)
    assert r.joints == tuple(load_spec("cat").names) and r.rate_hz == 100.0 and r.source == "sim"
    assert np.allclose(np.diff(r.t), 0.01)
    assert np.isnan(r.clock_phase[~r.stepping]).all() and (r.frequency_hz[~r.stepping] == 0).all()
    on = r.stepping
    assert ((r.clock_phase[on] >= 0) & (r.clock_phase[on] < 1)).all()
    assert set(np.unique(r.frequency_hz[on])) == {2.0, 2.5} and r.amplitude.max() == 0.5
    assert not r.stepping[r.t < 1.3].any() and r.stepping[(r.t > 1.4) & (r.t < 11.3)].all()
    assert not r.stepping[r.t >= 11.81].any() and r.contacts[r.t > 12.3].all()  # standing again, all feet down


def test_recording_is_deterministic():
    short = ((1.0, 0.0, 0.0), (1.5, 2.0, 0.5), (0.5, 0.0, 0.0))
    a, b = record_sim(short), record_sim(short)
    for f in dataclasses.fields(GaitRecording):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y, equal_nan=True), f.name
        else:
            assert x == y, f.name


def test_contact_frequency_matches_the_commanded_one(trot):
    f2 = contact_frequency(trot, 2.3, 6.3)  # after the ramp
    assert f2 == pytest.approx(2.0, rel=0.02)
    f25 = contact_frequency(trot, 7.0, 11.3)
    assert f25 == pytest.approx(2.5, rel=0.02)
    assert math.isnan(contact_frequency(trot, 0.0, 1.2))  # standing
    assert math.isnan(contact_frequency(dataclasses.replace(trot, contacts=None)))


def test_default_sets():
    for schedules in (TRAIN, HELDOUT):
        for name, segs in schedules.items():
            assert segs[0][1:] == (0.0, 0.0) and segs[0][0] >= 1.0, name
            SteppingController.scheduled(segs)
    steps = lambda sets: {(f, lift) for segs in sets.values() for _, f, lift in segs if f and lift}  # noqa: E731
    train, held = steps(TRAIN), steps(HELDOUT)
    assert {f for f, _ in train} >= {1.5, 2.0, 2.5} and {lift for _, lift in train} >= {0.35, 0.65}
    assert all(1.5 <= f <= 2.5 and 0.35 <= lift <= 0.65 for f, lift in train | held)
    assert not {f for f, _ in held} & {f for f, _ in train} and not {x for _, x in held} & {x for _, x in train}
    assert 150 <= schedule_seconds(TRAIN) <= 210 and 45 <= schedule_seconds(HELDOUT) <= 75
    # stand → trot → another frequency → stand
    assert any([bool(f) for _, f, _ in segs] == [False, True, True, False] and segs[1][1] != segs[2][1]
               for segs in HELDOUT.values())


# ------------------------------------------------------------------------------------------ files


def test_save_load_round_trip_and_splits(tmp_path, trot):
    log_like = dataclasses.replace(trot, name="from-a-log", source="log", split="log", contacts=None)
    path = save_recordings(tmp_path / "g.npz", [trot, log_like], set_name="mixed")
    back = load_recordings(path)
    assert [r.name for r in back] == ["trot", "from-a-log"] and back[1].contacts is None
    for f in dataclasses.fields(GaitRecording):
        x, y = getattr(trot, f.name), getattr(back[0], f.name)
        assert np.array_equal(x, y, equal_nan=True) if isinstance(x, np.ndarray) else x == y, f.name
    assert [r.name for r in load_recordings(path, split="log")] == ["from-a-log"]
    with pytest.raises(PhaseError, match="no recordings of split 'train'") as err:
        load_recordings(path, split="train")
    _one_line(err)


def test_corrupt_and_mismatched_files(tmp_path, trot):
    good = save_recordings(tmp_path / "good.npz", [trot]).read_bytes()
    cases = {"garbage.npz": b"not an npz at all", "cut.npz": good[: len(good) // 2]}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
    np.savez(tmp_path / "foreign.npz", t=np.zeros(3))
    arrays = dict(np.load(tmp_path / "good.npz"))
    arrays["meta"] = np.array(json.dumps({**json.loads(str(arrays["meta"])), "format": "other"}))
    np.savez(tmp_path / "format.npz", **arrays)
    arrays = dict(np.load(tmp_path / "good.npz"))
    arrays["q"] = arrays["q"][:, :5]
    np.savez(tmp_path / "shape.npz", **arrays)
    for name, match in (("garbage.npz", "not a gait-data file"), ("cut.npz", "corrupt|truncated"),
                        ("foreign.npz", "missing array"), ("format.npz", "format 'other'"),
                        ("shape.npz", "inconsistent"), ("missing.npz", "no such")):
        with pytest.raises(PhaseError, match=match) as err:
            load_recordings(tmp_path / name)
        assert str(tmp_path / name) in _one_line(err)
    other = dataclasses.replace(trot, joints=trot.joints[::-1], name="reversed")
    with pytest.raises(PhaseError, match="joints") as err:
        save_recordings(tmp_path / "mixed.npz", [trot, other])
    _one_line(err)
    assert not (tmp_path / "mixed.npz").exists()


# ------------------------------------------------------------------------------------------ logs


@pytest.fixture(scope="module")
def bus_log(tmp_path_factory):
    """The cat trotting in place through the virtual bus (the whole hardware path), wall clock, 50 Hz."""
    d = tmp_path_factory.mktemp("bus")
    ok(felis(d, "run", "step-in-place", "--robot", "cat", "--backend", "dxl", "--port", "virtual", "--log",
             "run.mcap", "--duration", "2.5", "--rate", "50", timeout=90))
    return d / "run.mcap"


def test_from_log_through_the_virtual_bus(bus_log):
    r = from_log(bus_log)
    assert r.source == "log" and r.name == "run" and r.rate_hz == 50.0  # the run's rate, from the summary
    assert r.joints == tuple(load_spec("cat").names) and r.contacts is None  # the servos report no contacts
    assert np.allclose(np.diff(r.t), 0.02) and 2.4 <= r.duration_s <= 2.5 and r.q.shape == (len(r.t), 12)
    assert np.isnan(r.clock_phase).all() and not r.stepping.any() and not r.amplitude.any()
    assert np.ptp(r.q[:, load_spec("cat").index("fl_roll")]) > 0.2  # the legs moved
    fine = from_log(bus_log, rate_hz=200.0)
    assert np.allclose(np.diff(fine.t), 0.005) and len(fine.t) > 3.5 * len(r.t)


def test_from_a_simulated_log_keeps_contacts_and_times(tmp_path):
    ok(felis(tmp_path, "run", "step-in-place", "--robot", "cat", "--log", "sim.mcap", "--duration", "4"))
    r = from_log(tmp_path / "sim.mcap")
    assert r.contacts is not None and r.contacts.shape == (400, 4) and r.rate_hz == 100.0
    assert np.allclose(np.diff(r.t), 0.01, rtol=0, atol=1e-9)  # on the grid already: kept as logged
    assert contact_frequency(r, 1.5, 4.0) == pytest.approx(2.0, rel=0.02)


def _write_log(path, spec, ts, q=None):
    with RunLog(path, spec) as log:
        for k, t in enumerate(ts):
            log.state(State(t=float(t), q=spec.pose("stand") if q is None else q[k], dq=np.zeros(spec.n)))
    return path


def test_from_log_errors(tmp_path):
    spec = load_spec("cat")
    ts = np.arange(300) * 0.01
    q = np.tile(spec.pose("stand"), (300, 1))
    q[123, spec.index("hr_roll")] = np.nan
    (tmp_path / "text.mcap").write_text("hello")
    cases = [
        (tmp_path / "missing.mcap", "no such run log"),
        (tmp_path / "text.mcap", "not an MCAP file"),
        (_write_log(tmp_path / "empty.mcap", spec, []), "no /joint_states messages"),
        (_write_log(tmp_path / "short.mcap", spec, ts[:150]), r"only 1\.49 s of states.*≥ 2 s"),
        (_write_log(tmp_path / "nan.mcap", spec, ts, q), r"joint hr_roll has no value \(NaN\) at t = 1\.230 s"),
        (_write_log(tmp_path / "back.mcap", spec, np.r_[ts[:50], ts[40:]]), "do not increase at message 50"),
    ]
    for path, match in cases:
        with pytest.raises(PhaseError, match=match) as err:
            from_log(path)
        _one_line(err)
    r = from_log(_write_log(tmp_path / "ok.mcap", spec, ts))  # regular times: kept as logged
    assert np.allclose(r.t, ts, rtol=0, atol=1e-9) and r.rate_hz == spec.rate_hz  # log times are whole ns


# ------------------------------------------------------------------------------------------ the command


def test_phase_record_cli(tmp_path, bus_log):
    r = ok(felis(tmp_path, "phase", "record", "--set", "heldout", "--scale", "0.1", "--out", "h.npz", "--json"))
    summary = json.loads(r.stdout)
    assert summary["set"] == "heldout" and [x["name"] for x in summary["recordings"]] == list(HELDOUT)
    recs = load_recordings(tmp_path / "h.npz", split="heldout")
    assert len(recs) == 3 and all(r.source == "sim" and r.contacts is not None for r in recs)
    assert sum(r.duration_s for r in recs) == pytest.approx(0.1 * schedule_seconds(HELDOUT) + 3 * BLEND_S, abs=0.1)
    r = ok(felis(tmp_path, "phase", "record", "--from-log", str(bus_log), "--from-log", str(bus_log),
                 "--out", "logs.npz"))
    assert "2 recording(s)" in r.stdout and "50 Hz" in r.stdout
    assert [x.split for x in load_recordings(tmp_path / "logs.npz")] == ["log", "log"]
    for args, fragment in ((("--out", "x.npz", "--from-log", str(bus_log), "--set", "train"), "--set and --scale"),
                           (("--out", "x.txt"), "must end in .npz"), (("--out", "x.npz", "--scale", "0"), "--scale"),
                           (("--out", "x.npz", "--from-log", "nope.mcap"), "no such run log")):
        r = felis(tmp_path, "phase", "record", *args)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0]
    assert not (tmp_path / "x.npz").exists() and not (tmp_path / "x.txt").exists()
