"""IMU mounting calibration (`felis.calib.imu`): the math, the validation, and the whole path — a
mis-mounted, drifting virtual IMU on the servo-in-the-loop bus, `ImuReader` on its pty,
`estimate_mounting`, and `DynamixelRobot` applying the result. Nothing is mocked: bad cases use the
real `RvcEmulator` with a misbehaving source."""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import pytest

from felis.calib.imu import ImuMounting, apply_mounting, estimate_mounting, mounting_from_gravity
from felis.cli.virtualbus import _imu_options
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.robot import IMU_MAX_AGE_S, Calibration, DynamixelRobot
from felis.drivers.imu import RATE_HZ, G, ImuReader, RvcEmulator, SensorMount
from felis.drivers.virtual import spawn
from felis.errors import CalibrationError, ParameterError
from felis.hal import Imu
from felis.rotations import (
    body_rate,
    quat_conj,
    quat_exp,
    quat_from_ypr,
    quat_log,
    quat_matrix,
    quat_mul,
    quat_rotate,
    ypr_from_quat,
)
from felis.sim import MujocoRobot
from felis.sim.servo_in_loop import virtual_bus
from felis.spec import load_spec

ROLL, PITCH = 6.0, -4.0  # degrees: the simulated mis-mounting
DRIFT = np.array([0.01, -0.02, 0.005])  # rad/s, sensor frame
UP = np.array([0.0, 0.0, G])


def _rpy(roll_deg: float, pitch_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
    return quat_from_ypr(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (°) of the rotation between two unit quaternions (sign-insensitive)."""
    d = quat_mul(quat_conj(a), b)
    return math.degrees(2 * math.atan2(float(np.linalg.norm(d[1:])), abs(d[0])))


def _tilt_deg(q: np.ndarray) -> float:
    """Angle (°) between the frame's z axis and the world's vertical."""
    z = quat_rotate(q, np.array([0.0, 0.0, 1.0]))
    return math.degrees(math.atan2(math.hypot(z[0], z[1]), z[2]))


def _vec_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


# --- pure math ---------------------------------------------------------------------------------------


def test_apply_mounting_undoes_any_mount_and_bias():
    rng = np.random.default_rng(4)
    for _ in range(50):
        q_wb = quat_exp(rng.uniform(-2, 2, 3))
        q_bs = quat_exp(rng.uniform(-1.5, 1.5, 3))
        w_b, a_b, bias = rng.normal(size=3), rng.normal(size=3) * 5, rng.normal(size=3) * 0.05
        q_ws, a_s = SensorMount(q_bs).sample(q_wb, a_b)  # what the sensor reports (no drift)
        w_s = quat_matrix(q_bs).T @ w_b + bias
        got = apply_mounting(Imu(quat=q_ws, gyro=w_s, accel=a_s), q_bs, bias)
        assert _angle_deg(got.quat, q_wb) < 1e-6
        assert got.gyro == pytest.approx(w_b, abs=1e-12) and got.accel == pytest.approx(a_b, abs=1e-12)
    same = apply_mounting(Imu(quat=q_ws, gyro=w_s, accel=a_s), None, None)  # nothing to apply: a copy
    assert np.array_equal(same.quat, q_ws) and np.array_equal(same.gyro, w_s) and same.gyro is not w_s


def test_tilt_signs_follow_the_right_hand_rule():
    # A sensor rolled +6° about the body's x reads +g·sin 6° on its y axis; pitched −4° about y, +g·sin 4° on x.
    _, a_s = SensorMount(_rpy(ROLL, 0)).sample(np.array([1.0, 0, 0, 0]), UP)
    assert a_s[1] == pytest.approx(G * math.sin(math.radians(ROLL))) and abs(a_s[0]) < 1e-12
    _, a_s = SensorMount(_rpy(0, PITCH)).sample(np.array([1.0, 0, 0, 0]), UP)
    assert a_s[0] == pytest.approx(G * math.sin(math.radians(-PITCH))) and abs(a_s[1]) < 1e-12
    for roll, pitch in [(ROLL, PITCH), (-20, 3), (0, 25), (12, 0)]:
        _, a_s = SensorMount(_rpy(roll, pitch)).sample(np.array([1.0, 0, 0, 0]), UP)
        m = ImuMounting(mounting_from_gravity(a_s), np.zeros(3))
        assert (m.roll_deg, m.pitch_deg) == pytest.approx((roll, pitch), abs=1e-9)
        assert _angle_deg(m.rotation, _rpy(roll, pitch)) < 1e-7
        assert m.tilt_deg == pytest.approx(math.degrees(math.acos(math.cos(math.radians(roll))
                                                                  * math.cos(math.radians(pitch)))))


def test_yaw_is_kept_and_a_mount_yaw_only_turns_the_level_body():
    q_bs = _rpy(ROLL, PITCH)
    for body_yaw in (0.0, 40.0, -170.0):
        q_ws, a_s = SensorMount(q_bs).sample(_rpy(0, 0, body_yaw), UP)
        est = ImuMounting(mounting_from_gravity(a_s), np.zeros(3))
        yaw, pitch, roll = np.degrees(ypr_from_quat(est.apply(Imu(q_ws, np.zeros(3), a_s)).quat))
        assert (roll, pitch, yaw) == pytest.approx((0, 0, body_yaw), abs=1e-7)
    # A yaw in the mount is not observable: the estimate has none, the corrected body is level but turned.
    q_ws, a_s = SensorMount(_rpy(ROLL, PITCH, 15.0)).sample(_rpy(0, 0, 40.0), UP)
    est = ImuMounting(mounting_from_gravity(a_s), np.zeros(3))
    assert (est.roll_deg, est.pitch_deg) == pytest.approx((ROLL, PITCH), abs=1e-9)
    body = est.apply(Imu(q_ws, np.zeros(3), a_s))
    assert _tilt_deg(body.quat) < 1e-7 and math.degrees(ypr_from_quat(body.quat)[0]) == pytest.approx(55.0)
    assert _vec_angle_deg(body.accel, UP) < 1e-7


def test_sensor_mount_drift_shows_as_a_constant_rate():
    mount = SensorMount(_rpy(ROLL, PITCH), DRIFT)
    q_wb = _rpy(3, -2, 30)
    samples = [mount.sample(q_wb, UP)[0] for _ in range(300)]
    for k in (1, 150, 299):
        assert body_rate(samples[k - 1], samples[k], 0.01) == pytest.approx(DRIFT, abs=1e-9)
    assert quat_log(quat_mul(quat_conj(samples[0]), samples[-1])) == pytest.approx(DRIFT * 2.99, abs=1e-12)
    with pytest.raises(ValueError, match="unit quaternion"):
        SensorMount(np.array([1.0, 0.1, 0, 0]))
    with pytest.raises(ValueError, match="3 finite"):
        SensorMount(drift=[0.0, math.nan, 0.0])


def test_to_dict_round_trip_and_validation():
    m = ImuMounting(_rpy(ROLL, PITCH), DRIFT, samples=150, duration_s=1.49, gravity_residual=-0.002)
    d = m.to_dict()
    assert d["yaw_observable"] is False and d["tilt_deg"] == pytest.approx(m.tilt_deg, abs=1e-4)
    assert all(type(v) is float for v in d["rotation"] + d["gyro_bias"])
    back = ImuMounting.from_dict(d)
    assert np.array_equal(back.rotation, m.rotation) and np.array_equal(back.gyro_bias, m.gyro_bias)
    assert (back.samples, back.duration_s, back.gravity_residual) == (150, 1.49, -0.002)
    # minimal table; −q is the same rotation (stored with w ≥ 0); a quaternion off by < 1e-3 is renormalised
    minimal = ImuMounting.from_dict({"rotation": list(-1.0005 * m.rotation), "gyro_bias": [0, 0, 0]})
    assert minimal.rotation == pytest.approx(m.rotation) and minimal.samples == 0
    bad = [
        ({"rotation": [1, 0, 0, 0]}, "cal.imu: missing 'gyro_bias'"),
        ({"rotation": [1, 0.1, 0, 0], "gyro_bias": [0, 0, 0]}, "cal.imu.rotation: not a unit quaternion"),
        ({"rotation": [1, 0, 0], "gyro_bias": [0, 0, 0]}, "cal.imu.rotation: expected 4 numbers, got 3"),
        ({"rotation": "1,0,0,0", "gyro_bias": [0, 0, 0]}, "cal.imu.rotation: expected 4 numbers"),
        ({"rotation": [1, 0, 0, 0], "gyro_bias": [0, math.inf, 0]}, "cal.imu.gyro_bias: values must be finite"),
        ({"rotation": [1, 0, 0, 0], "gyro_bias": [0, True, 0]}, "cal.imu.gyro_bias: expected 3 numbers"),
        ({"rotation": [1, 0, 0, 0], "gyro_bias": [0, 0, 0], "samples": -1}, "cal.imu.samples: expected an integer"),
        ({"rotation": [1, 0, 0, 0], "gyro_bias": [0, 0, 0], "yaw": 0}, "cal.imu: unknown key 'yaw'"),
        ({"rotation": [1, 0, 0, 0], "gyro_bias": [0, 0, 0], "yaw_observable": True},
         "cal.imu.yaw_observable: must be false"),
        ([1, 0, 0, 0], "cal.imu: expected a table"),
    ]
    for data, message in bad:
        with pytest.raises(CalibrationError) as e:
            ImuMounting.from_dict(data, where="cal.imu")
        assert str(e.value).startswith(message) and "\n" not in str(e.value), (data, str(e.value))


# --- estimate on a real emulator ---------------------------------------------------------------------


def _estimate_on(source, seconds: float = 0.6, **kw) -> ImuMounting:
    with RvcEmulator(source) as emu, ImuReader(emu.port) as reader:
        return estimate_mounting(reader, seconds, min_samples=20, **kw)


def test_no_frames_names_the_port():
    emu = RvcEmulator(lambda: (np.array([1.0, 0, 0, 0]), UP))  # never started: the port is silent
    try:
        with ImuReader(emu.port) as reader:
            t0 = time.monotonic()
            with pytest.raises(CalibrationError, match=f"no IMU frames on {emu.port} in 0.3 s.*UART-RVC") as e:
                estimate_mounting(reader, 2.0, first_frame_s=0.3)
            assert time.monotonic() - t0 < 1.0 and "\n" not in str(e.value)
    finally:
        emu.stop()


def test_a_moving_robot_is_rejected():
    t0 = time.monotonic()

    def wobble():
        t = time.monotonic() - t0
        q = quat_exp([0.3 * math.sin(2 * math.pi * 1.5 * t), 0.2 * math.sin(2 * math.pi * t), 0.0])
        return q, quat_rotate(quat_conj(q), UP)

    with pytest.raises(CalibrationError, match="the robot moved during the IMU calibration"):
        _estimate_on(wobble)


def test_a_steady_turn_is_not_a_bias():
    samples = iter(range(10**6))

    def turning():  # 0.5 rad/s about the vertical on the sensor's own sample clock: still accelerometer
        return quat_exp([0.0, 0.0, 0.5 * next(samples) / RATE_HZ]), UP

    with pytest.raises(CalibrationError, match="turned steadily at 0.5"):
        _estimate_on(turning)


def test_accel_far_from_g_is_rejected():
    with pytest.raises(CalibrationError, match=r"reads 2\.00 m/s² at rest, expected g"):
        _estimate_on(lambda: (np.array([1.0, 0, 0, 0]), np.array([0.0, 0.0, 2.0])))


def test_a_large_tilt_is_rejected():
    with virtual_bus("cat", sim=True, imu_mount=_rpy(-90, 0)) as bus, ImuReader(bus.imu_port) as reader:
        with pytest.raises(CalibrationError, match="tilted 90.0° .* not on a level surface or the IMU is mounted "
                                                   "on its side"):
            estimate_mounting(reader, 0.6, min_samples=20)


def test_virtual_mount_options_are_checked():
    with pytest.raises(ParameterError, match="sim=True"):
        virtual_bus("cat", imu_mount=_rpy(ROLL, PITCH))
    with pytest.raises(ParameterError, match="arm has none"):
        virtual_bus("arm", sim=True, imu_drift=DRIFT)
    with pytest.raises(ParameterError, match="unit quaternion"):
        spawn("cat", sim=True, imu_mount=[1.0, 1.0, 0.0, 0.0])
    opts = _imu_options(argparse.Namespace(imu_mount_deg="6,-4,10", imu_drift="0.01,-0.02,0.005"))
    assert _angle_deg(opts["imu_mount"], _rpy(6, -4, 10)) < 1e-9 and opts["imu_drift"] == (0.01, -0.02, 0.005)
    with pytest.raises(ParameterError, match="--imu-drift takes three comma-separated numbers"):
        _imu_options(argparse.Namespace(imu_mount_deg=None, imu_drift="0.01,x"))


# --- the whole path ----------------------------------------------------------------------------------
# The bus runs in its own process (`spawn`, i.e. `felis virtual-bus --imu-mount-deg … --imu-drift …`), as
# hardware would: in-process, its server thread would share the GIL with the IMU threads and the
# SDK's few-millisecond reply timeouts.


def _calibrated(spec, est: ImuMounting) -> Calibration:
    return Calibration(np.ones(spec.n), np.zeros(spec.n), imu_rotation=est.rotation, gyro_bias=est.gyro_bias)


def _robot(spec, bus, calibration: Calibration | None = None) -> DynamixelRobot:
    """The hardware robot on the spawned bus, with generous reply timeouts (a loaded 2-core CI machine)."""
    return DynamixelRobot(spec, bus.port, calibration=calibration, imu_port=bus.imu_port,
                          bus=DynamixelBus(bus.port, retries=3, timeout_margin_ms=50.0))


def test_mount_and_drift_are_recovered_and_applied_by_the_robot():
    spec = load_spec("cat")
    with spawn("cat", sim=True, imu_mount=_rpy(ROLL, PITCH), imu_drift=DRIFT) as bus:
        assert "IMU mounted at roll,pitch,yaw 6,-4,0°, IMU drifting 0.01,-0.02,0.005 rad/s" in bus.summary
        with ImuReader(bus.imu_port) as reader:
            est = estimate_mounting(reader, 1.5)
        print(f"\n{est.summary()}")
        assert est.samples >= 100 and est.duration_s == pytest.approx(1.5, abs=0.1)
        assert _angle_deg(est.rotation, _rpy(ROLL, PITCH)) < 0.5
        assert (est.roll_deg, est.pitch_deg) == pytest.approx((ROLL, PITCH), abs=0.5)
        assert est.gyro_bias == pytest.approx(DRIFT, rel=0.2, abs=0.001)
        assert abs(est.gravity_residual) < 0.05  # held still: the accelerometer reads g
        with _robot(spec, bus, _calibrated(spec, est)) as robot:
            assert robot.imu.wait(robot.imu.frames + 3)
            gyro, accel = [], []
            for _ in range(30):
                s = robot.read()
                gyro.append(s.imu.gyro)
                accel.append(s.imu.accel)
                time.sleep(0.01)
    # body frame: gravity straight up, no rate left (the orientation itself keeps its integrated drift)
    assert _vec_angle_deg(np.mean(accel, axis=0), UP) < 0.5
    assert np.linalg.norm(np.mean(gyro, axis=0)) < 0.005
    assert np.abs(gyro).max() < 0.05


def test_a_quiet_imu_is_no_reading_not_a_frozen_one():
    """The IMU emulator's thread stops (its source fails): the port stays open but goes quiet. The robot
    then reports no IMU reading instead of repeating the last orientation."""
    spec = load_spec("cat")
    with virtual_bus("cat", sim=True) as bus, _robot(spec, bus) as robot:
        assert robot.imu.wait(robot.imu.frames + 3) and robot.read().imu is not None

        def broken():
            raise RuntimeError("sensor failed")

        bus.imu.emulator.source = broken
        assert _wait_until(lambda: bus.imu.emulator.error is not None)
        time.sleep(IMU_MAX_AGE_S + 0.05)
        assert robot.read().imu is None and robot.imu.error is None  # quiet, not vanished


def _wait_until(cond, timeout: float = 2.0) -> bool:
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    return cond()


def test_calibrated_robot_reports_a_level_body():
    spec = load_spec("cat")
    with MujocoRobot(spec) as sim:
        q_true = sim.read().imu.quat  # the simulated upper body in its start pose: standing level
    with spawn("cat", sim=True, imu_mount=_rpy(ROLL, PITCH)) as bus:
        with ImuReader(bus.imu_port) as reader:
            est = estimate_mounting(reader, 1.0)
        with _robot(spec, bus) as raw:  # no IMU calibration
            assert raw.imu.wait(raw.imu.frames + 3)
            before = raw.read().imu
        with _robot(spec, bus, _calibrated(spec, est)) as robot:
            assert robot.imu.wait(robot.imu.frames + 3)
            after = robot.read().imu
    tilt = math.degrees(math.acos(math.cos(math.radians(ROLL)) * math.cos(math.radians(PITCH))))
    assert _tilt_deg(before.quat) == pytest.approx(tilt, abs=0.1)
    assert _tilt_deg(q_true) < 1e-6
    assert _tilt_deg(after.quat) < 0.5 and _angle_deg(after.quat, q_true) < 0.5
    assert _vec_angle_deg(after.accel, UP) < 0.5
