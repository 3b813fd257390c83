"""MuJoCo backend (`felis.sim`): models, servo model, `MujocoRobot`, scenarios, rendering.

Physics is kept apart from tasks: this package steps and measures a model; controllers never
import it. ``felis.sim.models`` holds the MJCF files named by the robot descriptions.

    robot.py          MujocoRobot: the HAL's Robot on a MuJoCo model (ModelMismatch)
    servo.py          the Dynamixel position servo as MuJoCo actuator and joint parameters (ServoParams)
    servo_file.py     servo parameter files, as ``felis sysid`` writes them (save/load_servo_params)
    bodymodel.py      load_body_model: the MJCF model -> felis.bodymodel.BodyModel
    scenarios.py      drop, push and pose applied to a simulated robot (apply_drop, push, set_pose)
    landing.py        a drop measured: ImpactRecorder, LandingRecorder, assess_landing
    pushes.py         push tests: Pusher, FallDetector, ThreadedPushTest
    servo_in_loop.py  the virtual bus's servos (and IMU) backed by the MuJoCo model (virtual_bus, MujocoBackend)
    render.py         VideoRecorder: offscreen rendering of a run to MP4, GIF or PNG
"""

from felis.sim.robot import ModelMismatch, MujocoRobot

__all__ = ["ModelMismatch", "MujocoRobot"]
