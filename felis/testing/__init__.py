"""felis.testing: sim-in-the-loop tests in a few lines (a pytest plugin, registered through ``pytest11``).

    plugin.py      the fixtures: sim_robot, virtual_bus, dxl_robot (factories), run, felis_stack
    resources.py   what the factories open, each on an ExitStack that closes it (usable outside pytest)
    runner.py      run_controller / RunResult: one run with its MCAP log, read back
    assertions.py  assert_joint_within, assert_event, assert_no_event, assert_no_fault on a run log

A test imports the assertions from here; the fixtures need no import (docs/testing.md)::

    from felis.testing import assert_event, assert_joint_within, assert_no_fault

    def test_the_arm_holds_through_the_servo_path(virtual_bus, dxl_robot, run):
        robot = dxl_robot(virtual_bus("arm", sim=True))
        res = run(robot, "hold", 1.0, rate=50)
        assert_no_fault(res)
        assert_event(res, "stopped", reason="duration")

Nothing here imports MuJoCo, the SDK or the Foxglove SDK at import time (the plugin loads in every pytest run).
"""

from felis.testing.assertions import (
    FAULT_EVENTS,
    assert_event,
    assert_joint_within,
    assert_no_event,
    assert_no_fault,
    faults_in,
    run_start,
)
from felis.testing.resources import VirtualPort, open_dxl_robot, open_sim_robot, open_virtual_bus
from felis.testing.runner import RunResult, run_controller

__all__ = ["FAULT_EVENTS", "RunResult", "VirtualPort", "assert_event", "assert_joint_within", "assert_no_event",
           "assert_no_fault", "faults_in", "open_dxl_robot", "open_sim_robot", "open_virtual_bus", "run_controller",
           "run_start"]
