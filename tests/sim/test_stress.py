"""Robustness: random drops with random joint commands never break the simulation.

A landing controller in training will throw the cat at the floor in every orientation while
commanding anything in range; the physics must stay finite and the bodies must not sink in.
The default run does a few dozen episodes; ``make test-slow`` does hundreds.
"""

import numpy as np
import pytest

from felis.hal import Command
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.sim.scenarios import drop, lowest_point
from felis.spec import load_spec

CAT = load_spec("cat")


class RandomTargets:
    """Jumps to a new random in-range target every 0.1 s (the safety layer rate-limits it)."""

    name = "random"

    def __init__(self, rng):
        self.rng = rng

    def reset(self, spec, state):
        self.q = state.q

    def __call__(self, state):
        if round(state.t * 100) % 10 == 0:
            self.q = self.rng.uniform(CAT.lower, CAT.upper)
        return Command(q=self.q)


class Floor:
    """Records the deepest any collision geometry got below the floor."""

    def __init__(self, robot):
        self.robot, self.deepest = robot, 0.0

    def __call__(self, state, command):
        self.deepest = min(self.deepest, lowest_point(self.robot.model, self.robot.data, self.robot.root_body))


def _episodes(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    with MujocoRobot(CAT) as cat:
        for _ in range(n):
            cat.reset()
            h = rng.uniform(0.2, 3.0)
            drop(cat, h, *rng.uniform(-180, 180, 3))
            floor = Floor(cat)
            report = run_loop(cat, RandomTargets(rng), duration=float(np.sqrt(2 * h / 9.81)) + 0.6,
                              monitors=[floor], keep_armed=True)
            assert report.ok
            assert np.all(np.isfinite(cat.data.qpos)) and np.all(np.isfinite(cat.data.qvel))
            assert floor.deepest > -0.025, f"sank {-floor.deepest * 1e3:.0f} mm from {h:.2f} m"
            assert np.all(np.abs(report.final_state.q) <= CAT.upper + 0.05)


def test_random_drops_and_commands():
    _episodes(25, seed=1)


@pytest.mark.slow
def test_random_drops_and_commands_many():
    _episodes(400, seed=2)
