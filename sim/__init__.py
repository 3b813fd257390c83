"""MuJoCo backend (`felis.sim`): models, servo model, `MujocoRobot`, scenarios, rendering.

Physics is kept apart from tasks: this package steps and measures a model; controllers never
import it. ``felis.sim.models`` holds the MJCF files named by the robot descriptions.
"""

from felis.sim.robot import ModelMismatch, MujocoRobot

__all__ = ["ModelMismatch", "MujocoRobot"]
