"""Push tests in MuJoCo: the loop monitors that apply a `felis.scenarios.Push` and watch for a fall.

`Pusher` and `FallDetector` act on a model the loop steps; `ThreadedPushTest` on the virtual bus's model,
which another thread steps. What counts as a fall is `felis.scenarios.verdicts.fall_reason`; this module
measures its inputs (the upper body's tilt, a body other than a foot on the floor) on the simulation.
"""

from __future__ import annotations

import mujoco
import numpy as np

from felis.rotations import tilt_from_up
from felis.scenarios.push import Push
from felis.scenarios.verdicts import fall_reason
from felis.sim.robot import MujocoRobot
from felis.sim.scenarios import push


class Pusher:
    """Loop monitor that applies ``push`` to the simulation once the run's clock reaches ``push.t_s``."""

    def __init__(self, robot: MujocoRobot, p: Push):
        self.robot, self.push = robot, p
        self.t: float | None = None  # when it was applied (run clock)

    def __call__(self, state, command) -> None:
        if self.t is None and state.t >= self.push.t_s - 1e-9:
            push(self.robot, self.push.body, self.push.impulse())
            self.t = state.t


class ThreadedPushTest:
    """The push and the fall detector for a model stepped in another thread (the virtual bus's).

    The loop monitor (``__call__``, in the loop's thread) only asks for the push when its clock reaches
    ``t_s``; the physics thread applies it between two steps and checks for a fall every
    ``check_every`` steps, through ``robot.substep_hook``: nothing touches the model mid-step. Times
    are mapped to the loop's clock by the push: t_loop = t_push_loop + (t_sim − t_push_sim).
    """

    def __init__(self, robot: MujocoRobot, p: Push, feet: tuple[str, ...], check_every: int = 5):
        self.robot, self.push, self.check_every = robot, p, check_every
        self.detector = FallDetector(robot, feet)
        self.t: float | None = None  # push, loop clock
        self._asked = False
        self._push_sim: float | None = None
        self._fall_sim: float | None = None
        self._n = 0
        robot.substep_hook = self._substep

    def __call__(self, state, command) -> None:
        if not self._asked and state.t >= self.push.t_s - 1e-9:
            self.t, self._asked = state.t, True

    def _substep(self, m, d) -> None:
        if self._asked and self._push_sim is None:
            push(self.robot, self.push.body, self.push.impulse())
            self._push_sim = float(d.time)
        self._n += 1
        if self._fall_sim is None and self._n % self.check_every == 0:
            why = self.detector.check()
            if why:
                self._fall_sim, self.detector.why = float(d.time), why

    def detach(self) -> None:
        self.robot.substep_hook = None

    @property
    def fall_t(self) -> float | None:
        """Fall time on the loop's clock (None: no fall, or it came before the push was applied)."""
        if self._fall_sim is None or self._push_sim is None or self.t is None:
            return None
        return self.t + (self._fall_sim - self._push_sim)


class FallDetector:
    """Loop monitor: the fall rule (`felis.scenarios.verdicts.fall_reason`) checked every tick on the simulation."""

    def __init__(self, robot: MujocoRobot, feet: tuple[str, ...], floor: str = "floor"):
        m = robot.model
        self.robot = robot
        self.floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, floor)
        foot_ids = {robot.body_id(f) for f in feet}
        self.foot_geom = np.array([m.geom_bodyid[g] in foot_ids for g in range(m.ngeom)])
        self.root = robot.root_body
        self.t: float | None = None  # first tick that met the fall condition (run clock)
        self.why = ""
        self.max_tilt_deg = 0.0

    def off_foot_body(self) -> str | None:
        """A body other than a foot touching the floor now, or None."""
        m, d = self.robot.model, self.robot.data
        for i in range(d.ncon):
            c = d.contact[i]
            other = c.geom2 if c.geom1 == self.floor else c.geom1 if c.geom2 == self.floor else -1
            if other >= 0 and not self.foot_geom[other]:
                return m.body(int(m.geom_bodyid[other])).name
        return None

    def check(self) -> str:
        """'' while standing, else why it counts as fallen now."""
        tilt = tilt_from_up(float(self.robot.data.xmat[self.root, 8]))
        self.max_tilt_deg = max(self.max_tilt_deg, tilt)
        return fall_reason(tilt, self.off_foot_body())

    def __call__(self, state, command) -> None:
        if self.t is None:
            why = self.check()
            if why:
                self.t, self.why = state.t, why
