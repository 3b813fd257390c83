"""Offscreen rendering of a simulated run to MP4, GIF or PNG.

`VideoRecorder` is a loop monitor: it renders a frame whenever simulated time passes the next
frame time (``fps``), from the model's ``track`` camera when there is one. Frames are written as
they come to a temporary file next to the target, renamed into place by `close` (a run that fails
half-way leaves no partial video). A ``.png`` target is a film strip: ``strip`` frames evenly
spaced over the run, side by side. ``markers`` (n, 3) world points, in order, are drawn as an orange line through
them in every frame (e.g. a tracking controller's target path; a line costs nothing against the scene, where 141
small spheres doubled a frame's time); ``start`` skips the first seconds of a run.
Frames are drawn without shadows and without the floor's reflection: in software OpenGL (a machine without a
GPU, ``MUJOCO_GL=egl``) they cost 3–4× the time of the rest of a frame (a 640×480 frame of the cat: 216 against
55 ms on 2 cores).

Needs an OpenGL context: on a machine without a display set ``MUJOCO_GL=egl`` (the CLI does).
"""

from __future__ import annotations

import os
from pathlib import Path

import imageio.v2 as imageio
import mujoco
import numpy as np

from felis.errors import ParameterError, RenderError
from felis.files import prepare_parent
from felis.hal import Command, State
from felis.sim.robot import MujocoRobot

FORMATS = (".mp4", ".gif", ".png")
PATH_RGBA = np.array([1.0, 0.55, 0.1, 0.9], dtype=np.float32)  # the markers' line: orange
PATH_WIDTH_PX = 3.0


def check_video_path(path: str | Path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ParameterError(f"{path}: output must end in {', '.join(FORMATS)}")
    return path


class VideoRecorder:
    """Renders frames during a run; ``close()`` writes the file."""

    def __init__(self, robot: MujocoRobot, path: str | Path, fps: float = 30.0, width: int = 640,
                 height: int = 480, camera: str = "track", strip: int = 6, markers: np.ndarray | None = None,
                 start: float = 0.0):
        self.path = check_video_path(path)
        if not 1 <= fps <= 120:
            raise ParameterError(f"fps must be within 1…120, got {fps}")
        self.robot, self.fps, self.strip = robot, float(fps), strip
        m = robot.model
        try:
            self.renderer = mujoco.Renderer(m, height, width)
        except Exception as e:  # noqa: BLE001 - GL errors come as several types
            raise RenderError(f"cannot render offscreen ({e}); set MUJOCO_GL=egl, or run `felis doctor`") from None
        cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        self.camera: int | str = cam if cam >= 0 else -1
        self.markers = None if markers is None else np.asarray(markers, dtype=float).reshape(-1, 3)
        self.frames: list[np.ndarray] = []  # kept only for PNG strips
        self.count = 0
        self.start = max(0.0, float(start))  # the first frame this long into the run (a demo skips a still start)
        self._next = None
        prepare_parent(self.path, "video")
        self._tmp = self.path.with_name(f".{self.path.stem}.part{self.path.suffix}")
        self._writer = None
        if self.path.suffix.lower() in (".mp4", ".gif"):
            kwargs = {"fps": self.fps}
            if self.path.suffix.lower() == ".mp4":
                kwargs.update(codec="libx264", quality=7, macro_block_size=8, format="FFMPEG")
            else:
                kwargs.update(format="GIF", loop=0)
                kwargs["duration"] = 1000.0 / self.fps
                kwargs.pop("fps")
            self._writer = imageio.get_writer(self._tmp, **kwargs)

    def reset(self, spec, state: State) -> None:
        self._next = state.t + self.start

    def capture(self) -> np.ndarray:
        self.renderer.update_scene(self.robot.data, camera=self.camera)
        flags = self.renderer.scene.flags  # no shadows, no floor reflection: 3-4× faster frames in software GL
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        if self.markers is not None:
            self._draw_path(self.renderer.scene)
        return self.renderer.render()

    def _draw_path(self, scn) -> None:
        """The markers as a polyline: one line geom per segment, as many as the scene has room for (one point alone
        is no segment: nothing is drawn)."""
        line = mujoco.mjtGeom.mjGEOM_LINE
        for a, b in zip(self.markers[:-1], self.markers[1:], strict=True):
            if scn.ngeom >= scn.maxgeom:
                break
            g = scn.geoms[scn.ngeom]
            mujoco.mjv_initGeom(g, line, np.zeros(3), np.zeros(3), np.eye(3).ravel(), PATH_RGBA)
            mujoco.mjv_connector(g, line, PATH_WIDTH_PX, a, b)
            scn.ngeom += 1

    def __call__(self, state: State, command: Command) -> None:
        if self._next is None:
            self._next = state.t + self.start
        if state.t + 1e-9 < self._next:
            return
        self._next += 1.0 / self.fps
        frame = self.capture()
        self.count += 1
        if self._writer is not None:
            self._writer.append_data(frame)
        else:
            self.frames.append(frame)

    def close(self) -> Path:
        """Finish the file and move it into place."""
        try:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
            else:
                if not self.frames:
                    self.frames.append(self.capture())
                pick = np.linspace(0, len(self.frames) - 1, min(self.strip, len(self.frames))).round().astype(int)
                imageio.imwrite(self._tmp, np.concatenate([self.frames[i] for i in pick], axis=1), format="PNG")
            os.replace(self._tmp, self.path)
        finally:
            self.renderer.close()
        return self.path

    def abort(self) -> None:
        """Drop the partial file (after a failed run)."""
        try:
            if self._writer is not None:
                self._writer.close()
        finally:
            self._tmp.unlink(missing_ok=True)
            self.renderer.close()
