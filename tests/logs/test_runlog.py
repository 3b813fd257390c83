"""Run logs (felis.logs.runlog) and their plot (felis.logs.plot): round trip, crash safety, errors.

Real MCAP files in tmp_path; the crash test SIGKILLs a real child process mid-run and measures what it lost.
"""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from felis.errors import LogError
from felis.hal import Command, Faults, Imu, State
from felis.logs.mcap import MAGIC
from felis.logs.messages import as_dict
from felis.logs.plot import plot_log
from felis.logs.reader import LogData, log_info, protobuf_class, read_log
from felis.logs.runlog import RunLog
from felis.rotations import tilt_deg
from felis.spec import load_spec

RATE = 100.0


@pytest.fixture(scope="module")
def spec():
    return load_spec("cat")


def make_state(i: int, n: int) -> State:
    t = i / RATE
    k = np.arange(n)
    q = 0.3 * np.sin(2 * np.pi * 0.5 * t + k) + 1e-3 * k
    dq = 0.3 * np.pi * np.cos(2 * np.pi * 0.5 * t + k)
    roll = 0.2 * np.sin(t)
    quat = np.array([np.cos(roll / 2), np.sin(roll / 2), 0.0, 0.0])
    faults = Faults(hardware=np.where(k == 3, 4 if i == 150 else 0, 0).astype(np.int32), comm_errors=i // 100)
    return State(t=t, q=q, dq=dq, effort=0.01 * q, height=0.25 - 0.1 * t / 2,
                 imu=Imu(quat=quat, gyro=np.array([0.2 * np.cos(t), 0.0, 0.0]), accel=np.array([0, 0, 9.81])),
                 contacts=np.array([True, True, i % 2 == 0, False]), faults=faults)


def make_command(i: int, n: int) -> Command:
    return Command(q=0.3 * np.sin(2 * np.pi * 0.5 * (i + 1) / RATE + np.arange(n)), dq_max=np.full(n, 5.0))


def write_run(path: Path, spec, ticks: int = 200, summary: dict | None = None) -> list[State]:
    states = []
    with RunLog(path, spec, meta={"scenario": "unit", "seed": 7}) as log:
        for i in range(ticks):
            s = make_state(i, spec.n)
            states.append(s)
            log.state(s)
            log.command(s.t, make_command(i, spec.n))
            if i == 50:
                log.event(s.t, "clamp", joints=["tail_yaw"], by=np.float64(0.02))
            if i in (120, 121):
                log.event(s.t, "watchdog", reason="read failures", count=np.int64(i))
        log.close(summary)
    return states


# ---------------------------------------------------------------------------------------------
# round trip


def test_round_trip(tmp_path, spec):
    path = tmp_path / "run.mcap"
    summary = {"ticks": 200, "overruns": 0, "mean_ms": 0.4}
    states = write_run(path, spec, summary=summary)
    data = read_log(path)
    assert isinstance(data, LogData)
    assert data.complete is True
    assert data.joints == list(spec.names)
    assert data.meta["robot"] == "cat" and data.meta["scenario"] == "unit" and data.meta["seed"] == 7
    assert data.meta["rate_hz"] == spec.rate_hz
    assert "felis_version" in data.meta and "started_utc" in data.meta
    assert data.meta["groups"]["tail"] == ["tail_pitch", "tail_yaw"]
    np.testing.assert_array_equal(data.t, [s.t for s in states])
    np.testing.assert_array_equal(data.q, np.stack([s.q for s in states]))
    np.testing.assert_array_equal(data.dq, np.stack([s.dq for s in states]))
    np.testing.assert_array_equal(data.effort, np.stack([s.effort for s in states]))
    np.testing.assert_array_equal(data.height, [s.height for s in states])
    np.testing.assert_array_equal(data.quat, np.stack([s.imu.quat for s in states]))
    np.testing.assert_array_equal(data.cmd_t, data.t)
    np.testing.assert_array_equal(data.cmd_q, np.stack([make_command(i, spec.n).q for i in range(200)]))
    assert data.q.shape == (200, 12) and data.quat.shape == (200, 4)
    assert data.counts == {"/meta": 1, "/joint_states": 200, "/joint_commands": 200, "/log": 3, "/summary": 1,
                           "/imu": 200, "/contacts": 200, "/base": 200, "/faults": 4}  # faults: when they change
    assert data.feet == list(spec.sensors.contacts) and data.contacts.shape == (200, 4)
    np.testing.assert_array_equal(data.contacts, np.stack([s.contacts for s in states]))
    assert data.start_ns > 1_600_000_000 * 10**9  # epoch nanoseconds, not 1970
    assert data.summary == summary
    assert [e["kind"] for e in data.events] == ["clamp", "watchdog", "watchdog"]
    assert data.events[0] == {"t": 0.5, "kind": "clamp", "detail": {"joints": ["tail_yaw"], "by": 0.02}}
    assert data.events[2]["detail"] == {"reason": "read failures", "count": 121}


def test_opens_with_standard_mcap_reader(tmp_path, spec):
    """The plain `mcap` reader: a summary with statistics, chunk indexes (an indexed file), Foxglove's schemas."""
    path = tmp_path / "run.mcap"
    write_run(path, spec, ticks=60, summary={"ok": True})
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes  # chunked and indexed
        assert all(ci.compression == "lz4" for ci in summary.chunk_indexes)
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) >= {"/meta", "/joint_states", "/joint_commands", "/log", "/imu", "/contacts", "/summary"}
        kinds = {t: (c.message_encoding, summary.schemas[c.schema_id].name) for t, c in topics.items()}
        assert kinds["/joint_states"] == kinds["/joint_commands"] == ("protobuf", "foxglove.JointStates")
        assert kinds["/log"] == ("protobuf", "foxglove.Log")
        assert kinds["/imu"] == ("protobuf", "felis.Imu") and kinds["/meta"] == ("json", "felis.Meta")
        assert summary.statistics.channel_message_counts[topics["/joint_states"].id] == 60
        msgs = list(reader.iter_messages(topics=["/imu"]))
        meta = next(reader.iter_messages(topics=["/meta"]))[2]
    assert len(msgs) == 60
    _, _, message = msgs[5]
    assert message.log_time == meta.log_time + 50_000_000  # epoch ns: start + run time
    schema = summary.schemas[topics["/imu"].schema_id]
    body = as_dict(protobuf_class(schema.name, schema.data).FromString(message.data))
    assert set(body) == {"orientation", "angular_velocity", "linear_acceleration", "tilt_deg"}
    assert set(body["orientation"]) == {"x", "y", "z", "w"}  # Foxglove's order, by name


def test_optional_fields_absent(tmp_path, spec):
    """A state with only t, q, dq (e.g. the arm without sensors) reads back with None arrays."""
    path = tmp_path / "bare.mcap"
    with RunLog(path, spec) as log:
        for i in range(5):
            log.state(State(t=i * 0.01, q=np.zeros(spec.n), dq=np.ones(spec.n)))
    data = read_log(path)
    assert data.effort is None and data.height is None and data.quat is None
    assert data.cmd_q.shape == (0, spec.n) and data.summary is None and data.complete


def test_close_is_idempotent_and_exit_closes_on_exception(tmp_path, spec):
    path = tmp_path / "boom.mcap"
    with pytest.raises(RuntimeError):
        with RunLog(path, spec) as log:
            log.state(make_state(0, spec.n))
            raise RuntimeError("controller blew up")
    log.close()
    log.close({"late": 1})  # already closed: no effect
    data = read_log(path)
    assert data.complete and data.counts["/joint_states"] == 1 and data.summary is None
    with pytest.raises(LogError, match="closed"):
        log.state(make_state(1, spec.n))


# ---------------------------------------------------------------------------------------------
# crash safety

CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from felis.hal import Command, Imu, State
    from felis.logs.mcap import FLUSH_WALL_S
    from felis.logs.runlog import RunLog
    from felis.spec import load_spec
    spec = load_spec("cat")
    stop, paced = int(sys.argv[2]), sys.argv[3] == "paced"
    log = RunLog(sys.argv[1], spec)
    imu = Imu(quat=np.array([1.0, 0, 0, 0]), gyro=np.zeros(3), accel=np.array([0, 0, 9.81]))
    t0 = time.monotonic()
    wall = []
    i = 0
    while i <= stop if paced else time.monotonic() - t0 < 0.3:  # fast: as many ticks as 0.3 s of wall time takes
        t = i * 0.01
        if paced:  # as hardware runs: tick i at t0 + t
            time.sleep(max(0.0, t0 + t - time.monotonic()))
        wall.append(time.monotonic())
        log.state(State(t=t, q=np.full(spec.n, float(i)), dq=np.zeros(spec.n), height=0.2, imu=imu))
        log.command(t, Command(q=np.full(spec.n, float(i))))
        if i % 25 == 0:
            log.event(t, "tick", i=i)
        i += 1
    stop = i - 1
    recent = sum(w > wall[-1] - 2 * FLUSH_WALL_S for w in wall)  # the ticks of the last 2 FLUSH_WALL_S of wall time
    print(stop, recent, flush=True)   # ticks 0..stop are logged: the parent kills us now, while we wait
    sys.stdin.readline()
""")


@pytest.mark.parametrize("stop, pace", [(37, "paced"), (160, "paced"), (None, "fast")])
def test_killed_process_loses_at_most_the_flush_interval(tmp_path, stop, pace):
    """SIGKILL right after tick ``stop`` was logged (the child waits for it, so no race): the log holds every
    tick up to a few before, in order, without gaps. A run at the pace of the clock loses at most 2 FLUSH_S of run
    time plus two ticks (the chunk being filled and the one the writer thread may not have written yet); one faster
    than real time at most its last 2 FLUSH_WALL_S of wall time, plus two ticks and twice FLUSH_S / 4 of run time."""
    from felis.logs.mcap import FLUSH_S

    path = tmp_path / "crash.mcap"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path), str(stop or 0), pace], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        told, recent = (int(x) for x in proc.stdout.readline().split())
        assert stop is None or told == stop, "child writer died early"
        stop = told
        proc.kill()  # SIGKILL: no cleanup, no close()
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -9
    data = read_log(path)
    assert data.complete is False and data.summary is None
    kept = len(data.t)
    lost = stop + 1 - kept
    bound = round(2 * FLUSH_S / 0.01) + 2 if pace == "paced" else recent + 2 + 2 * math.ceil(FLUSH_S / 4 / 0.01)
    print(f"SIGKILL after {stop + 1} ticks ({pace}): {kept} in the file, {lost} lost (bound {bound})")
    assert 0 <= lost <= bound, f"lost {lost} ticks of {stop + 1}"
    assert kept > 0, "a chunk should have been finished"
    assert len(data.cmd_t) == kept and data.quat is not None and len(data.height) == kept
    np.testing.assert_array_equal(data.q[:, 0], np.arange(kept))  # no gaps, in order
    np.testing.assert_allclose(data.t, np.arange(kept) * 0.01, atol=1e-9)
    assert data.events and data.events[0]["kind"] == "tick"
    info = log_info(path)  # what `felis log info` shows of a cut file
    assert info["complete"] is False and info["counts"]["/joint_states"] == kept


def test_cut_anywhere_reads_a_prefix_or_raises_log_error(tmp_path, spec):
    """Truncating a log at any byte gives the states before the cut, or LogError before /meta."""
    path = tmp_path / "full.mcap"
    write_run(path, spec, ticks=20, summary={"ok": True})
    raw = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    last = 0
    cuts = sorted(set(range(0, len(raw), 37)) | set(range(len(raw) - 40, len(raw))))
    for cut in cuts:
        cut_path.write_bytes(raw[:cut])
        try:
            data = read_log(cut_path)
        except LogError as e:
            assert str(cut_path) in str(e)
            assert last == 0, f"cut at {cut} raised after earlier cuts read fine"
            continue
        assert data.complete is False
        assert len(data.t) >= last
        last = len(data.t)
        expected = [make_state(i, spec.n).q for i in range(last)]
        np.testing.assert_array_equal(data.q, np.reshape(expected, (last, spec.n)))
    assert last == 20
    assert read_log(path).complete is True


def _chunks(raw: bytes) -> list[tuple[int, int]]:
    """(offset, record end) of each Chunk record of a whole MCAP file."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(raw):
        (length,) = struct.unpack_from("<Q", raw, pos + 1)
        if raw[pos] == 0x06:
            out.append((pos, pos + 9 + length))
        pos += 9 + length
    return out


def test_killed_while_a_chunk_header_is_overwritten_reads_the_chunks_before(tmp_path, spec):
    """The SDK's writer streams a chunk after a placeholder header (``2**64 - 1`` for the record length and the
    three sizes, 0 for the times) and overwrites the header field by field when the chunk is done. A kill at any
    byte of that overwrite leaves every byte of the chunk in the file under a half-written header (seen once in
    CI, as an OverflowError from the mcap reader): the reader keeps the chunks before it and says the log is cut."""
    path = tmp_path / "full.mcap"
    with RunLog(path, spec, meta={"scenario": "unit"}) as log:
        for i in range(30):
            log.state(make_state(i, spec.n))
            if i % 10 == 9:
                log.flush()  # a chunk per ten ticks
        log.close()
    raw = path.read_bytes()
    chunks = _chunks(raw)
    assert len(chunks) >= 3
    cut_path = tmp_path / "cut.mcap"
    for k, (start, end) in enumerate(chunks):
        before = 0
        if k:
            cut_path.write_bytes(raw[:chunks[k - 1][1]])
            before = len(read_log(cut_path).t)
        body = start + 9
        (name_len,) = struct.unpack_from("<I", raw, body + 24 + 4)
        head = 9 + 28 + 4 + name_len + 8
        placeholder = bytearray(raw[start:start + head])
        struct.pack_into("<Q", placeholder, 1, 2**64 - 1)
        struct.pack_into("<QQQI", placeholder, 9, 0, 0, 2**64 - 1, 2**32 - 1)
        struct.pack_into("<Q", placeholder, head - 8, 2**64 - 1)
        for done in range(head):  # the first ``done`` bytes of the header overwritten
            header = raw[start:start + done] + bytes(placeholder[done:])
            cut_path.write_bytes(raw[:start] + header + raw[start + head:end])
            if k == 0:  # the chunk with /meta, written when the log opens
                with pytest.raises(LogError, match="meta"):
                    read_log(cut_path)
                continue
            data = read_log(cut_path)
            assert data.complete is False and len(data.t) == before, (k, done)
        cut_path.write_bytes(raw[:end])  # the header finished: the chunk is read
        assert len(read_log(cut_path).t) > before or k == 0


# ---------------------------------------------------------------------------------------------
# non-finite numbers


def test_non_finite_numbers(tmp_path, spec):
    """Protobuf channels keep NaN and ±inf; JSON ones (which have neither) write null or leave the field out,
    read back as NaN."""
    path = tmp_path / "nan.mcap"
    q = np.zeros(spec.n)
    q[3] = np.nan
    dq = np.zeros(spec.n)
    dq[0] = np.inf
    with RunLog(path, spec) as log:
        log.state(make_state(0, spec.n))
        log.state(State(t=0.01, q=q, dq=dq, height=float("nan"),
                        imu=Imu(quat=np.array([np.nan, 0, 0, 0]), gyro=np.zeros(3), accel=np.zeros(3))))
        log.command(0.01, Command(q=q))
        log.event(0.01, "nonfinite", values=q, where=float("-inf"))
        log.state(make_state(2, spec.n))
    data = read_log(path)
    assert np.isnan(data.q[1, 3]) and np.isfinite(np.delete(data.q[1], 3)).all()
    assert data.dq[1, 0] == np.inf and np.isnan(data.height[1]) and np.isnan(data.quat[1, 0])
    assert np.isnan(data.cmd_q[0, 3])
    assert "where" not in data.events[0]["detail"] and data.events[0]["detail"]["values"][3] is None
    assert data.effort is not None and np.isnan(data.effort[1]).all()  # the middle state had none
    assert len(data.t) == 3 and data.complete
    # the JSON channels are strict JSON: no NaN literal anywhere
    with open(path, "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            if channel.message_encoding == "json":
                json.loads(message.data, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))


# ---------------------------------------------------------------------------------------------
# errors


def test_missing_file(tmp_path):
    path = tmp_path / "nope.mcap"
    with pytest.raises(LogError, match="no such run log") as e:
        read_log(path)
    assert str(path) in str(e.value)


@pytest.mark.parametrize("content", [b"", b"time,q0\n0.0,1.0\n", b"\x89MCAP0"])
def test_not_an_mcap_file(tmp_path, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(LogError) as e:
        read_log(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_mcap_file_that_is_not_a_felis_log(tmp_path):
    path = tmp_path / "other.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        ch = w.register_channel("/chatter", "json", sid)
        w.add_message(ch, log_time=0, data=b'{"a": 1}', publish_time=0)
        w.finish()
    with pytest.raises(LogError, match="not a felis run log") as e:
        read_log(path)
    assert str(path) in str(e.value)


def test_directory_is_not_a_log(tmp_path):
    with pytest.raises(LogError, match="not a file"):
        read_log(tmp_path)


def test_unwritable_target(tmp_path, spec):
    blocker = tmp_path / "plain.txt"
    blocker.write_text("a regular file")
    target = blocker / "runs" / "run.mcap"
    with pytest.raises(LogError) as e:
        RunLog(target, spec)
    assert str(target) in str(e.value)
    with pytest.raises(LogError):
        RunLog(tmp_path, spec)  # a directory


def test_creates_parent_directories(tmp_path, spec):
    path = tmp_path / "a" / "b" / "run.mcap"
    write_run(path, spec, ticks=3)
    assert read_log(path).counts["/joint_states"] == 3


# ---------------------------------------------------------------------------------------------
# info and plot


def test_log_info(tmp_path, spec):
    path = tmp_path / "run.mcap"
    write_run(path, spec, summary={"overruns": 2})
    info = log_info(path)
    json.dumps(info)  # JSON-able
    assert info["path"] == str(path) and info["robot"] == "cat" and info["joints"] == list(spec.names)
    assert info["complete"] is True
    assert math.isclose(info["duration_s"], 1.99)
    assert math.isclose(info["rate"], RATE)
    assert info["counts"]["/joint_states"] == 200 and info["counts"]["/joint_commands"] == 200
    assert info["events"] == {"clamp": 1, "watchdog": 2}
    assert info["summary"] == {"overruns": 2}
    assert info["size_bytes"] == path.stat().st_size > 0


def test_tilt():
    half = np.radians(30) / 2
    quats = np.array([[1, 0, 0, 0], [np.cos(half), np.sin(half), 0, 0], [np.cos(half), 0, np.sin(half), 0],
                      [np.cos(half), 0, 0, np.sin(half)], [0, 1, 0, 0], [2, 0, 0, 0]], dtype=float)
    np.testing.assert_allclose(tilt_deg(quats), [0, 30, 30, 0, 180, 0], atol=1e-9)


def test_plot_log(tmp_path, spec):
    path = tmp_path / "run.mcap"
    write_run(path, spec, summary={"ok": True})
    out = tmp_path / "plots" / "run.png"
    assert plot_log(path, out) == out
    png = out.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert os.listdir(out.parent) == ["run.png"]  # no temp file left behind


def test_plot_of_cut_and_bare_logs(tmp_path, spec):
    path = tmp_path / "cut.mcap"
    write_run(path, spec, ticks=40)
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) * 2 // 3])
    assert plot_log(path, tmp_path / "cut.png").read_bytes()[:4] == b"\x89PNG"
    bare = tmp_path / "bare.mcap"
    RunLog(bare, spec).close()  # no states at all
    assert plot_log(bare, tmp_path / "bare.png").stat().st_size > 0


def test_plot_of_bad_log_raises_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_text("not a log")
    with pytest.raises(LogError, match="not an MCAP file"):
        plot_log(bad, tmp_path / "out" / "bad.png")
    assert not (tmp_path / "out").exists()


def test_a_felis_0_2_log_is_refused_with_what_to_do(tmp_path):
    path = tmp_path / "old.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        meta = w.register_channel("/meta", "json", w.register_schema("felis.Meta", "jsonschema", b"{}"))
        state = w.register_channel("/state", "json", w.register_schema("felis.State", "jsonschema", b"{}"))
        w.add_message(meta, log_time=0, data=b'{"robot": "cat", "joints": ["a"]}', publish_time=0)
        w.add_message(state, log_time=0, data=b'{"t": 0, "q": [0], "dq": [0]}', publish_time=0)
        w.finish()
    with pytest.raises(LogError, match=r"felis 0\.2 log.*felis==0\.2") as e:
        read_log(path)
    assert "\n" not in str(e.value)
