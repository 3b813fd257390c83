"""BNO08x UART-RVC driver: frame codec, parser resynchronisation, Euler conventions, reader on a pty."""

from __future__ import annotations

import errno
import math
import os
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from felis.drivers.imu import (
    FRAME_LEN,
    G,
    ImuReader,
    RvcEmulator,
    RvcParser,
    checksum,
    decode_frame,
    encode_frame,
    frames_between,
)
from felis.errors import CommError
from felis.rotations import body_rate, quat_conj, quat_from_ypr, quat_mul, quat_rotate, ypr_from_quat

# By hand from the spec: AA AA | index 5 | yaw 10.00° = 1000 = 0x03E8 | pitch -5.00° = -500 = 0xFE0C |
# roll 1.00° = 100 = 0x0064 | accel x 0, y 0, z 1000 mg = 0x03E8 | reserved 00 00 00 |
# checksum (05+E8+03+0C+FE+64+00+00+00+00+E8+03+00+00+00) = 841 = 0x349 -> 0x49.
GOLDEN = bytes.fromhex("AA AA 05 E8 03 0C FE 64 00 00 00 00 00 E8 03 00 00 00 49")
# The example message in the BNO080 datasheet (1000-3927, §1.3.5.2).
DATASHEET = bytes.fromhex("AA AA DE 01 00 92 FF 25 08 8D FE EC FF D1 03 00 00 00 E7")

angle = st.floats(-math.pi, math.pi, exclude_max=True, allow_nan=False)


def _frame(index=0, yaw=0.0, pitch=0.0, roll=0.0, accel=(0.0, 0.0, G)) -> bytes:
    return encode_frame(index, yaw, pitch, roll, accel)


def _rot_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) of the rotation between two unit quaternions (sign-insensitive)."""
    d = quat_mul(quat_conj(a), b)
    return 2 * math.atan2(float(np.linalg.norm(d[1:])), abs(d[0]))


def _axis_quat(axis, a) -> np.ndarray:
    return np.array([math.cos(a / 2), *(math.sin(a / 2) * np.asarray(axis, dtype=float))])


def _wrapped_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


# --- frames -------------------------------------------------------------------------------------------


def test_golden_frame_built_by_hand():
    assert len(GOLDEN) == FRAME_LEN
    assert encode_frame(5, 10.0, -5.0, 1.0, (0.0, 0.0, G)) == GOLDEN
    f = decode_frame(GOLDEN)
    assert f.index == 5
    assert (math.degrees(f.yaw), math.degrees(f.pitch), math.degrees(f.roll)) == pytest.approx((10, -5, 1), abs=1e-12)
    assert f.accel == pytest.approx([0, 0, G], abs=1e-12)
    assert f.reserved == b"\0\0\0" and f.raw == GOLDEN


def test_datasheet_example_frame():
    assert checksum(DATASHEET[2:18]) == 0xE7
    f = decode_frame(DATASHEET)
    assert f.index == 222
    assert np.degrees([f.yaw, f.pitch, f.roll]) == pytest.approx([0.01, -1.10, 20.85], abs=1e-9)
    assert f.accel == pytest.approx(np.array([-371, -20, 977]) * G / 1000, abs=1e-12)
    assert encode_frame(f.index, *np.degrees([f.yaw, f.pitch, f.roll]), f.accel) == DATASHEET


def test_checksum_covers_index_through_reserved():
    for i in range(2, FRAME_LEN):
        bad = bytearray(GOLDEN)
        bad[i] ^= 0x01
        with pytest.raises(ValueError):
            decode_frame(bytes(bad))
    assert checksum(bytes(range(16))) == sum(range(16)) % 256
    assert encode_frame(0, 0, 0, 0, (0, 0, 0), reserved=b"\x01\x02\x03")[15:] == b"\x01\x02\x03\x06"


def test_encode_wraps_yaw_and_rejects_out_of_range_values():
    assert decode_frame(_frame(yaw=180.0)).yaw == pytest.approx(-math.pi)
    assert decode_frame(_frame(yaw=-180.0)).yaw == pytest.approx(-math.pi)
    assert decode_frame(_frame(index=257)).index == 1
    for bad in (dict(pitch=400.0), dict(roll=-330.0), dict(pitch=math.nan), dict(accel=(0, 0, 40 * G))):
        with pytest.raises(ValueError):
            _frame(**bad)


def test_decode_values_are_what_the_wire_says():
    """Out-of-sensor-range but valid int16 values are decoded as they are, not clamped or wrapped."""
    f = decode_frame(_frame(pitch=300.0, roll=-300.0, accel=(30 * G, -30 * G, 0)))
    assert math.degrees(f.pitch) == pytest.approx(300.0) and math.degrees(f.roll) == pytest.approx(-300.0)
    assert f.accel == pytest.approx([30 * G, -30 * G, 0], abs=0.005)


# --- conventions and round trips ----------------------------------------------------------------------


def test_euler_is_intrinsic_z_y_x():
    y, p, r = 0.7, -0.4, 1.1
    expected = quat_mul(quat_mul(_axis_quat([0, 0, 1], y), _axis_quat([0, 1, 0], p)), _axis_quat([1, 0, 0], r))
    assert quat_from_ypr(y, p, r) == pytest.approx(expected, abs=1e-12)
    # right-hand rule: yaw +90° turns x into y; pitch +90° turns x into -z; roll +90° turns y into z
    assert quat_rotate(quat_from_ypr(math.pi / 2, 0, 0), [1, 0, 0]) == pytest.approx([0, 1, 0], abs=1e-12)
    assert quat_rotate(quat_from_ypr(0, math.pi / 2, 0), [1, 0, 0]) == pytest.approx([0, 0, -1], abs=1e-12)
    assert quat_rotate(quat_from_ypr(0, 0, math.pi / 2), [0, 1, 0]) == pytest.approx([0, 0, 1], abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(angle, st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3), angle)
def test_euler_quat_euler_round_trip(yaw, pitch, roll):
    y, p, r = ypr_from_quat(quat_from_ypr(yaw, pitch, roll))
    assert -math.pi <= y < math.pi and -math.pi <= r < math.pi
    assert _wrapped_diff(y, yaw) < 1e-9 and abs(p - pitch) < 1e-9 and _wrapped_diff(r, roll) < 1e-9


unit = st.floats(-1, 1, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(st.tuples(unit, unit, unit, unit).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_quat_euler_quat_round_trip(v):
    q = np.array(v) / np.linalg.norm(v)
    assert _rot_angle(q, quat_from_ypr(*ypr_from_quat(q))) < 1e-7


def test_gimbal_lock():
    for pitch in (math.pi / 2, -math.pi / 2):
        q = quat_from_ypr(0.3, pitch, -0.5)
        y, p, r = ypr_from_quat(q)
        assert p == pytest.approx(pitch) and r == 0.0
        assert _rot_angle(q, quat_from_ypr(y, p, r)) < 1e-9
    with pytest.raises(ValueError):
        ypr_from_quat([0, 0, 0, 0])


@settings(max_examples=200, deadline=None)
@given(st.tuples(unit, unit, unit, unit).filter(lambda v: np.linalg.norm(v) > 0.1),
       st.tuples(*[st.floats(-30 * G, 30 * G)] * 3), st.integers(0, 255))
def test_wire_round_trip_within_quantisation(v, accel, index):
    """quat -> yaw/pitch/roll -> 0.01° on the wire -> quat: each angle is off by ≤ 0.005°, so the
    composed rotation by ≤ 0.015°; accel by ≤ 0.5 mg."""
    q = np.array(v) / np.linalg.norm(v)
    f = decode_frame(encode_frame(index, *np.degrees(ypr_from_quat(q)), accel))
    assert f.index == index
    assert math.degrees(_rot_angle(q, f.quat)) <= 0.015 + 1e-9
    assert np.abs(f.accel - accel).max() <= 0.5e-3 * G + 1e-12


def test_body_rate_from_quaternion_difference():
    w = np.array([0.3, -1.2, 2.0])
    q0 = quat_from_ypr(0.5, 0.2, -0.3)
    dt = 0.01
    q1 = quat_mul(q0, _axis_quat(w / np.linalg.norm(w), np.linalg.norm(w) * dt))  # body-frame rotation
    assert body_rate(q0, q1, dt) == pytest.approx(w, rel=1e-9)
    assert body_rate(q0, -q1, dt) == pytest.approx(w, rel=1e-9)  # q and -q are the same orientation
    assert body_rate(q0, q0, dt) == pytest.approx([0, 0, 0], abs=1e-12)


def test_frames_between_counts_gaps_and_wraps():
    assert frames_between(10, 11, 0.01, 100) == 1
    assert frames_between(255, 2, 0.03, 100) == 3
    assert frames_between(10, 14, 0.0, 100) == 4  # burst: receive times say nothing
    assert frames_between(10, 10, 0.0, 100) == 0  # repeat
    assert frames_between(10, 11, 2.57, 100) == 257  # one full wrap of silence


# --- parser -------------------------------------------------------------------------------------------


def test_parser_garbage_prefix_and_byte_by_byte():
    stream = b"\x00\x13\xaa\x55\xff" + _frame(1) + _frame(2, yaw=-33.3) + _frame(3)
    p = RvcParser()
    frames = p.feed(stream)
    assert [f.index for f in frames] == [1, 2, 3] and p.dropped_bytes == 5
    p = RvcParser()
    got = [f for b in stream for f in p.feed(bytes([b]))]
    assert [f.index for f in got] == [1, 2, 3] and got[1].raw == _frame(2, yaw=-33.3)
    assert p.dropped_bytes == 5 and p.bad_checksums == 0


def test_parser_false_headers():
    # pitch = 0xAAAA (-218.46°): AA AA inside the payload
    tricky = _frame(7, pitch=-218.46)
    assert tricky[5:7] == b"\xaa\xaa"
    # in sync: the payload's AA AA is never looked at
    p = RvcParser()
    assert [f.index for f in p.feed(_frame(6) + tricky + _frame(8))] == [6, 7, 8] and p.bad_checksums == 0
    # out of sync: a truncated frame whose payload holds AA AA, then real frames
    p = RvcParser()
    assert [f.index for f in p.feed(tricky[2:12] + _frame(8) + tricky)] == [8, 7]
    assert p.bad_checksums >= 1 and p.dropped_bytes == 10
    # garbage ending in AA just before a header: AA AA AA
    p = RvcParser()
    assert [f.index for f in p.feed(b"\x01\xaa" + _frame(9))] == [9]


def test_parser_corrupted_checksum_is_counted_and_skipped():
    bad = bytearray(_frame(2))
    bad[18] ^= 0xFF
    p = RvcParser()
    assert [f.index for f in p.feed(_frame(1) + bytes(bad) + _frame(3))] == [1, 3]
    assert p.bad_checksums == 1 and p.dropped_bytes == FRAME_LEN and p.frames == 2


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.binary(max_size=40), st.integers(0, 255).map(lambda i: _frame(i, yaw=i - 100.0))),
                max_size=12),
       st.lists(st.integers(1, 25), min_size=1, max_size=8))
def test_parser_fuzz_never_raises_and_only_returns_valid_frames(parts, cuts):
    stream = b"".join(parts)
    p = RvcParser()
    frames, i, k = [], 0, 0
    while i < len(stream):  # feed in arbitrary chunk sizes
        n = cuts[k % len(cuts)]
        frames += p.feed(stream[i:i + n])
        i, k = i + n, k + 1
    for f in frames:
        assert len(f.raw) == FRAME_LEN and f.raw[:2] == b"\xaa\xaa"
        assert checksum(f.raw[2:18]) == f.raw[18] and f.raw in stream
    assert p.dropped_bytes + FRAME_LEN * len(frames) + len(p._buf) == len(stream)
    assert len(p._buf) < FRAME_LEN
    # chunking does not change the result
    assert [f.raw for f in RvcParser().feed(stream)] == [f.raw for f in frames]


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.binary(max_size=30).map(lambda b: b.replace(b"\xaa", b"")), st.integers(0, 255))))
def test_parser_recovers_every_frame_between_garbage_without_headers(items):
    stream = b"".join(g + _frame(i) for g, i in items)
    assert [f.index for f in RvcParser().feed(stream)] == [i for _, i in items]


# --- emulator and reader on a pty ---------------------------------------------------------------------


def _wait(cond, timeout=2.0) -> bool:
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    return cond()


class _Turntable:
    """Source: IMU tilted (pitch 10°, roll -20°) turning about world z at a constant rate.

    Time is the sensor's own sample clock (call count / rate), as on the real BNO08x."""

    def __init__(self, omega: float = 1.0, rate_hz: float = 100.0):
        self.omega, self.rate_hz, self.history = omega, rate_hz, []
        self.tilt = quat_from_ypr(0.0, math.radians(10), math.radians(-20))

    def __call__(self):
        q = quat_mul(_axis_quat([0, 0, 1], self.omega * len(self.history) / self.rate_hz), self.tilt)
        self.history.append(q)
        return q, quat_rotate(quat_conj(q), [0.0, 0.0, G])  # specific force of gravity, IMU frame

    def gyro(self) -> np.ndarray:
        return quat_rotate(quat_conj(self.tilt), [0.0, 0.0, self.omega])  # constant in the IMU frame


def test_end_to_end_emulator_to_reader_then_port_vanishes():
    source = _Turntable(omega=1.0)
    emu = RvcEmulator(source).start()
    try:
        reader = ImuReader(emu.port)
        assert reader.wait(frames=30, timeout=3.0)
        live = reader.latest()
        assert live is not None and not reader.stale(max_age=0.5)
    finally:
        emu.stop()  # the pty goes away, as when a USB adapter is unplugged
    try:
        assert _wait(lambda: reader.error is not None)
        assert emu.port in reader.error and "\n" not in reader.error
        assert reader.stale() and reader.age() >= 0
        f, imu = reader.latest_frame(), reader.latest()  # still the last reading
        assert imu is not None and f is not None
        assert len(source.history) < 256  # so the frame index is the sample number
        q_sent = source.history[f.index]
        assert math.degrees(_rot_angle(imu.quat, q_sent)) < 0.02
        expected = source.gyro()
        assert np.linalg.norm(imu.gyro - expected) < 0.1 * np.linalg.norm(expected)
        assert imu.accel == pytest.approx(quat_rotate(quat_conj(q_sent), [0, 0, G]), abs=0.01)
        assert reader.lost_frames == 0 and reader.bad_checksums == 0 and reader.frames >= 30
    finally:
        reader.close()
    assert reader.stale()


def test_read_keeps_an_impact_that_falls_between_two_ticks():
    """One frame of 100 m/s² among still ones: `latest()` has moved past it by the next tick, `read()`
    reports the mean of the frames since the previous read, so the impact shows."""
    still, spike_at = [0.0, 0.0, G], 30
    n = 0

    def source():
        nonlocal n
        n += 1
        return np.array([1.0, 0.0, 0.0, 0.0]), [0.0, 0.0, 100.0] if n == spike_at else still

    with RvcEmulator(source) as emu, ImuReader(emu.port) as reader:
        assert reader.wait(frames=5, timeout=3.0) and reader.frames < spike_at
        assert reader.read().accel == pytest.approx(still, abs=0.01)
        assert reader.wait(frames=spike_at + 5, timeout=3.0)
        assert reader.latest().accel == pytest.approx(still, abs=0.01)  # the latest frame alone: still
        got = reader.read().accel  # mean of ≥ 30 frames, one of them the spike
        assert got[2] > G + 1.0 and got[2] <= G + (100.0 - G) / (spike_at - 5) + 0.01
        assert reader.read().accel == pytest.approx(still, abs=0.01)  # the next tick: still again


def test_reader_counts_injected_faults():
    with RvcEmulator(_Turntable(), drop_rate=0.3, corrupt_rate=0.3, seed=3) as emu, ImuReader(emu.port) as reader:
        assert reader.wait(frames=20, timeout=3.0)
        assert _wait(lambda: reader.lost_frames > 0 and reader.bad_checksums + reader.dropped_bytes > 0)
        assert reader.latest() is not None and reader.error is None
    assert emu.dropped > 0 and emu.corrupted > 0


def _decodes(b: bytes) -> bool:
    try:
        decode_frame(b)
    except ValueError:
        return False
    return True


def test_emulator_frames_and_faults_offline():
    """The emulator's frames fed straight to the parser: drops leave index gaps, corruptions fail."""
    emu = RvcEmulator(_Turntable(), drop_rate=0.2, corrupt_rate=0.2, seed=1)
    try:
        frames = [emu.frame() for _ in range(200)]
    finally:
        emu.stop()
    got = RvcParser().feed(b"".join(b for b in frames if b is not None))
    assert emu.dropped == frames.count(None) > 0 and emu.corrupted > 0
    clean = [i for i, b in enumerate(frames) if b is not None and _decodes(b)]
    assert [f.index for f in got] == clean
    lost = sum(frames_between(a.index, b.index, 0.0, 100) - 1 for a, b in zip(got, got[1:], strict=False))
    assert lost == clean[-1] - clean[0] - (len(clean) - 1) > 0


def test_emulator_does_not_block_when_nobody_reads():
    emu = RvcEmulator(_Turntable(), rate_hz=1e6).start()  # as fast as it can: fills the pty buffer
    try:
        assert _wait(lambda: emu.overflows > 0, timeout=5.0)
        assert emu.error is None and emu._thread.is_alive()
    finally:
        t0 = time.monotonic()
        emu.stop()
    assert time.monotonic() - t0 < 1.0


def test_missing_port_raises_comm_error_naming_it(tmp_path):
    port = str(tmp_path / "ttyIMU0")
    with pytest.raises(CommError, match="no such device") as e:
        ImuReader(port)
    assert port in str(e.value) and "\n" not in str(e.value)


def test_regular_file_is_not_a_serial_device(tmp_path):
    path = tmp_path / "notatty"
    path.write_bytes(b"")
    with pytest.raises(CommError, match="not a serial device") as e:
        ImuReader(str(path))
    assert str(path) in str(e.value)


def test_permission_denied_names_port(tmp_path, monkeypatch):
    path = tmp_path / "ttyIMU1"
    path.write_bytes(b"")
    path.chmod(0)
    if os.geteuid() == 0:  # root ignores file permissions: raise what pyserial raises for EACCES
        def denied(port, *args, **kwargs):
            raise serial.SerialException(errno.EACCES, f"could not open port {port}: [Errno 13] Permission denied")
        monkeypatch.setattr(serial, "Serial", denied)
    with pytest.raises(CommError, match="permission denied") as e:
        ImuReader(str(path))
    assert str(path) in str(e.value) and "\n" not in str(e.value)
