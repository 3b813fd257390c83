"""An example of sim-in-the-loop tests written with felis.testing alone (docs/testing.md).

The fixtures (``sim_robot``, ``virtual_bus``, ``dxl_robot``, ``run``) come from the felis pytest plugin, which
pytest loads by itself once felis is installed: nothing to import for them. Everything a test builds is closed
when it ends, pass or fail: robots with torque off, buses stopped.
"""

from felis.testing import assert_event, assert_joint_within, assert_no_event, assert_no_fault


def test_the_cat_stands_up_in_simulation(sim_robot, run):
    res = run(sim_robot("cat"), "stand", 1.5)  # MuJoCo, simulated time: as fast as it steps
    assert_no_fault(res)
    assert_event(res, "stopped", reason="duration")
    assert_joint_within(res, "tail_pitch", 0.4, 0.6, t=(1.0, None))  # raised to the stand pose's 0.5 rad
    assert_joint_within(res, "spine_pitch", -0.1, 0.1)  # the spine stays level all the way
    assert_no_event(res, "limit_clamp")  # the controller never asked for more than the joints allow


def test_the_arm_stands_through_the_whole_servo_path(virtual_bus, dxl_robot, run):
    # dynamixel-sdk → pseudo-terminal → emulated servos → MuJoCo, on the wall clock like real servos
    vb = virtual_bus("arm", sim=True)
    robot = dxl_robot(vb, timeout_margin_ms=100)  # a loaded CI machine may answer late
    res = run(robot, "stand", 1.2, rate=50)
    assert_joint_within(res, "joint4", 0.5, 0.7, t=(1.0, None))  # the stand pose's 0.6 rad
    assert_no_fault(res, comm_errors=3)  # a busy machine may lose a reply or two, never more


def test_a_servo_switched_off_mid_run_stops_the_cat(virtual_bus, dxl_robot, run):
    vb = virtual_bus("cat", faults="torque_off=7@0.3")  # ID 7's torque goes off 0.3 s after it came on
    res = run(dxl_robot(vb, timeout_margin_ms=100), "hold", 1.0, rate=50)
    assert not res.ok and "fr_pitch (ID 7)" in res.report.stopped
    assert_event(res, "torque_lost", t=(0.25, None))
    assert_event(res, "torque_off", verified=True)  # the rest were switched off, and read back off
