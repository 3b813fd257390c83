"""System identification of the simulated servo model (`felis.sim.servo`) from step and chirp responses.

Each servo-driven joint's model is fitted to how the servo answered a test signal: the firmware's Position
P, I, D Gain (control-table units, through the same controller code the virtual bus and MuJoCo run), damping,
armature, friction, torque limit and latency. Timing: on a virtual bus whose servos run on a `StepClock`, every
tick is written and read at the emulator's own time (no host timing in the recording: load-proof); on
hardware the host's clock with a fitted latency. One concept per module:

    clock.py       the emulator's simulated clock (StepClock) that `record` advances

    model.py       the identified model: PARAMS, BOUNDS, the datasheet values (default_params), with_params
    excitation.py  the test signal per joint: steps, saturating steps, a chirp (Excitation, plan)
    recording.py   the excitation run on any HAL Robot and recorded (record, Recording, .npz files)
    replay.py      a recording's commands replayed in MuJoCo with sub-step timing (Replay, simulate)
    fit.py         least squares per joint on replay vs recording (fit, FitResult, fit_summary)

Parameter files are written by `felis.sim.servo_file`. ``felis sysid`` (``felis/cli/sysid.py``) wires it all
for an operator.
"""

from felis.calib.sysid.clock import StepClock
from felis.calib.sysid.excitation import KINDS, STEP_KINDS, Excitation, Plan, amplitudes, hold_pose, plan
from felis.calib.sysid.fit import FitResult, JointFit, fit, fit_summary
from felis.calib.sysid.model import (
    BOUNDS,
    GAINS,
    LOG,
    PARAMS,
    check_joints,
    default_params,
    gains,
    with_gains,
    with_params,
)
from felis.calib.sysid.recording import LATENCY_S, RECORDING_SCHEMA, SETUPS, TIMEBASES, Recording, record
from felis.calib.sysid.replay import Replay, bench_model, simulate

__all__ = [
    "BOUNDS", "GAINS", "KINDS", "LATENCY_S", "SETUPS", "LOG", "PARAMS", "RECORDING_SCHEMA", "STEP_KINDS", "TIMEBASES",
    "Excitation", "FitResult", "JointFit", "Plan", "Recording", "Replay", "StepClock", "amplitudes", "bench_model",
    "check_joints", "default_params", "fit", "fit_summary", "gains", "hold_pose", "plan", "record", "simulate",
    "with_gains", "with_params",
]
