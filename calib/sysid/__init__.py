"""System identification of the simulated servo model (`felis.sim.servo`) from step and chirp responses.

Each servo-driven joint's model (gain, damping, armature, friction, torque limit) is fitted to how the
servo answered a test signal. One concept per module:

    model.py       the identified model: PARAMS, BOUNDS, the datasheet values (default_params), with_params
    excitation.py  the test signal per joint: steps, saturating steps, a chirp (Excitation, plan)
    recording.py   the excitation run on any HAL Robot and recorded (record, Recording, .npz files)
    replay.py      a recording's commands replayed in MuJoCo with sub-step timing (Replay, simulate)
    fit.py         least squares per joint on replay vs recording (fit, FitResult, fit_summary)

Parameter files are written by `felis.sim.servo_file`. ``felis sysid`` (``felis/cli/sysid.py``) wires it all
for an operator.
"""

from felis.calib.sysid.excitation import KINDS, STEP_KINDS, Excitation, Plan, amplitudes, hold_pose, plan
from felis.calib.sysid.fit import FitResult, JointFit, fit, fit_summary
from felis.calib.sysid.model import BOUNDS, PARAMS, check_joints, default_params, with_params
from felis.calib.sysid.recording import LATENCY_S, RECORDING_SCHEMA, Recording, record
from felis.calib.sysid.replay import Replay, simulate

__all__ = [
    "BOUNDS", "KINDS", "LATENCY_S", "PARAMS", "RECORDING_SCHEMA", "STEP_KINDS", "Excitation", "FitResult", "JointFit",
    "Plan", "Recording", "Replay", "amplitudes", "check_joints", "default_params", "fit", "fit_summary", "hold_pose",
    "plan", "record", "simulate", "with_params",
]
