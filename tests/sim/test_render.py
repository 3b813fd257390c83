"""`felis.sim.render.VideoRecorder` as a loop monitor: frames at the frame rate of simulated time, from ``start``."""

from __future__ import annotations

import pytest

from felis.controllers import PoseController
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.sim.render import VideoRecorder
from felis.spec import load_spec


@pytest.mark.parametrize(("start", "frames"), [(0.0, 5), (0.3, 2)])
def test_frames_follow_simulated_time_from_the_start_given(tmp_path, start, frames):
    with MujocoRobot(load_spec("cat")) as robot:
        rec = VideoRecorder(robot, tmp_path / "strip.png", fps=10, width=64, height=48, start=start)
        run_loop(robot, PoseController("stand"), duration=0.5, rate_hz=100, monitors=[rec])
        assert rec.count == frames  # t = 0, 0.1 … 0.4, or 0.3 and 0.4 (a still start left out)
        assert rec.close().read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_markers_are_drawn_as_an_orange_line_through_the_points(tmp_path):
    import numpy as np

    from felis.controllers.arm_track import ArmTrackController, trajectory_from

    path = ArmTrackController(trajectory_from("figure8")).markers
    with MujocoRobot(load_spec("arm")) as robot:
        robot.reset()

        def orange(markers):
            rec = VideoRecorder(robot, tmp_path / "a.png", width=160, height=120, markers=markers)
            try:
                f = rec.capture().astype(int)
                return int(((f[..., 0] > 180) & (f[..., 1] > 90) & (f[..., 1] < 170) & (f[..., 2] < 80)).sum())
            finally:
                rec.close()

        assert orange(None) == 0
        assert orange(path) > 40  # the figure eight seen from the track camera
        many = np.repeat(path, 100, axis=0)  # more segments than the scene has room for: drawn until it is full
        assert orange(many) > 40
