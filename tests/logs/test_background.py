"""The log's writer thread (`felis.logs.background`): jobs in order, slices on the writer when nudged, the rest on
the caller, errors handed over, the interpreter's switch interval restored; and a run log written through it equals
one written on the loop's thread."""

from __future__ import annotations

import math
import sys
import threading
import time

import numpy as np
import pytest

from felis.errors import LogError
from felis.logs import mcap
from felis.logs.background import SWITCH_S, Background
from felis.logs.reader import read_log
from felis.logs.runlog import RunLog
from felis.spec import load_spec


def _job(tag: str, n: int, seen: list):
    for i in range(n):
        seen.append((tag, i, threading.current_thread().name))
        yield


def _wait(cond, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.001)
    return True


def test_jobs_run_in_order_on_the_writer_when_nudged_and_drain_finishes_them_here():
    before = sys.getswitchinterval()
    seen: list = []
    bg = Background(name="test-writer")
    try:
        assert sys.getswitchinterval() == pytest.approx(min(before, SWITCH_S), abs=1e-9)
        bg.submit(_job("a", 50, seen))
        bg.submit(_job("b", 50, seen))
        bg.nudge()
        assert _wait(lambda: len(seen) > 0), "the writer never ran"
        bg.drain()  # what is left, on this thread, after the writer's running slice
        assert not bg.pending
        assert [(t, i) for t, i, _ in seen] == [("a", i) for i in range(50)] + [("b", i) for i in range(50)]
        assert seen[0][2] == "test-writer"
        assert bg.slices >= 1
    finally:
        bg.close()
    assert not bg._thread.is_alive()
    assert sys.getswitchinterval() == before
    bg.close()  # idempotent


def test_an_error_on_the_writer_is_raised_once_on_the_callers_next_check_and_drops_the_queue():
    seen: list = []

    def bad():
        yield
        raise OSError("disk full")

    bg = Background()
    try:
        bg.submit(bad())
        bg.submit(_job("after", 3, seen))
        bg.nudge()
        assert _wait(lambda: bg.error is not None)
        with pytest.raises(OSError, match="disk full"):
            bg.check()
        bg.check()  # once
        assert not bg.pending and seen == []
    finally:
        bg.close()


def _run(path, spec, how: str, ticks: int = 120, sleep: float = 0.001):
    """A run of ``ticks`` at 100 Hz with a short sleep each tick (the writer's chance, as a physics step's), logged
    by `RunLog.tick` (``how`` 'tick') or by `state`, `command`, `timing`; returns the writer's slice count."""
    rng = np.random.default_rng(3)
    from felis.hal import Command, Imu, State

    log = RunLog(path, spec)
    slices = 0
    for i in range(ticks):
        t = i / 100
        s = State(t=t, q=rng.normal(size=spec.n), dq=rng.normal(size=spec.n), effort=rng.normal(size=spec.n),
                  height=0.2 + 0.01 * i, contacts=rng.random(4) > 0.5,
                  imu=Imu(quat=np.array([1.0, 0, 0, 0]), gyro=rng.normal(size=3), accel=np.array([0, 0, 9.81])))
        c = Command(q=rng.normal(size=spec.n))
        if how == "tick":
            log.tick(s, c, 1e-4 * i)
        else:
            log.state(s)
            log.command(t, c)
            log.timing(t, 1e-4 * i)
        if i == 60:
            log.event(t, "clamp", joints=["tail_yaw"])
        time.sleep(sleep)
        if log._bg is not None:
            slices = log._bg.slices
    log.close({"ticks": ticks})
    return slices


@pytest.mark.parametrize("mode", ["writer", "fast", "inline"])
@pytest.mark.parametrize("how", ["tick", "parts"])
def test_a_run_log_written_by_the_writer_thread_equals_one_written_on_the_loop(tmp_path, monkeypatch, mode, how):
    """'writer': every chunk through the writer thread (`mcap.FAST` infinite: as a run at the clock's pace);
    'fast': a run far faster than real time finishes its chunks on its own thread and never starts a writer;
    'inline': without `mcap.BACKGROUND`."""
    spec = load_spec("cat")
    ref = tmp_path / "ref.mcap"
    monkeypatch.setattr(mcap, "BACKGROUND", False)
    _run(ref, spec, "parts")
    monkeypatch.setattr(mcap, "BACKGROUND", mode != "inline")
    if mode == "writer":
        monkeypatch.setattr(mcap, "FAST", math.inf)
    path = tmp_path / "run.mcap"
    if mode == "fast":  # 0.5 ms a 10 ms tick: ~20 times faster than real time, past a few chunk boundaries
        seen, flushes = [], []
        monkeypatch.setattr(mcap.McapLog, "_handoff", lambda self: seen.append(1))
        flush = mcap.McapLog.flush
        monkeypatch.setattr(mcap.McapLog, "flush", lambda self: (flushes.append(1), flush(self))[1])
        assert _run(path, spec, how, sleep=0.0005) == 0 and seen == [], "a run this fast should not start a writer"
        assert len(flushes) > 2, "no chunk was finished mid-run (2: the log's opening)"
    else:
        slices = _run(path, spec, how)
        assert (slices > 0) == (mode == "writer"), "the writer thread wrote nothing"
    a, b = read_log(ref), read_log(path)
    assert a.complete and b.complete
    assert a.counts == b.counts and a.counts["/joint_states"] == 120 and a.counts["/timing"] == 120
    for field in ("t", "q", "dq", "effort", "height", "quat", "contacts", "cmd_t", "cmd_q"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert a.events == b.events and b.summary == {"ticks": 120}


def test_an_error_in_deferred_work_on_the_writer_stops_the_run_with_a_log_error(tmp_path, monkeypatch):
    monkeypatch.setattr(mcap, "FAST", math.inf)  # chunks through the writer, however fast this runs
    spec = load_spec("cat")
    from felis.hal import Command, State

    def broken():
        raise OSError("No space left on device")

    log = RunLog(tmp_path / "run.mcap", spec)
    log.defer(broken)
    with pytest.raises(LogError, match=r"cannot write run log .*run\.mcap: No space left on device"):
        for i in range(2000):
            log.tick(State(t=i / 100, q=np.zeros(spec.n), dq=np.zeros(spec.n)), Command(q=np.zeros(spec.n)), 0.0)
            time.sleep(0.001)
    log.close()  # the rest is written and the file finished
    data = read_log(tmp_path / "run.mcap")
    assert data.complete and 0 < data.counts["/joint_states"] <= i + 1


def test_a_log_dropped_without_close_ends_its_writer_and_restores_the_switch_interval(tmp_path, monkeypatch):
    import gc

    monkeypatch.setattr(mcap, "FAST", math.inf)
    from felis.hal import Command, State

    before = sys.getswitchinterval()
    spec = load_spec("cat")
    log = RunLog(tmp_path / "run.mcap", spec)
    for i in range(40):
        log.tick(State(t=i / 100, q=np.zeros(spec.n), dq=np.zeros(spec.n)), Command(q=np.zeros(spec.n)), 0.0)
        time.sleep(0.002)
    bg = log._bg
    assert bg is not None and sys.getswitchinterval() < before
    assert _wait(lambda: (bg.nudge(), not bg.pending)[1])  # the writer writes what it was handed when nudged
    del log
    gc.collect()
    bg._thread.join(timeout=5)
    assert not bg._thread.is_alive()
    assert sys.getswitchinterval() == pytest.approx(before, abs=1e-9)
