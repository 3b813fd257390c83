"""felis: ROS-free robot control for Dynamixel servos and MuJoCo through one HAL.

Core (this package): robot descriptions (`felis.spec`), HAL types (`felis.hal`), the control loop
(`felis.loop`) and its safety layer (`felis.safety`), rotations (`felis.rotations`), errors (`felis.errors`).
Subpackages: `felis.scenarios` (tasks and verdicts), `felis.logs` (run logs), `felis.sim` (MuJoCo backend),
`felis.drivers` (Dynamixel bus), `felis.controllers`, `felis.learning`, `felis.calib`, `felis.cli`.
"""

from felis.errors import FelisError
from felis.hal import Command, Imu, Lifecycle, Robot, State
from felis.spec import JointSpec, RobotSpec, load_spec

__version__ = "0.3.0"
__all__ = ["Command", "FelisError", "Imu", "JointSpec", "Lifecycle", "Robot", "RobotSpec", "State",
           "load_spec"]
