"""Controllers and monitors (`felis.controllers`): pure functions of HAL state and time.

They import only `felis` (and `felis.learning` for inference), never a backend, so each runs
unchanged on simulated and real robots. `make_controller` builds one by name for the CLI.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

from felis.controllers.pose import PoseController
from felis.errors import ParameterError
from felis.hal import Controller


def _arm_track(trajectory="figure8", weights=None, lead_in: float | None = None) -> Controller:
    """The arm following a tool-point trajectory (a builtin name, a CSV file or a Trajectory) with the
    learned IK pipeline (weights: the shipped ones unless a file is given)."""
    from felis.controllers.arm_track import LEAD_IN, ArmTrackController, trajectory_from
    from felis.learning.ik_solver import IkSolver

    return ArmTrackController(trajectory_from(trajectory), IkSolver.load(weights),
                              lead_in=LEAD_IN if lead_in is None else lead_in)


CONTROLLERS: dict[str, Callable[..., Controller]] = {
    "hold": lambda: PoseController("hold"),
    "stand": lambda: PoseController("stand", duration=0.5),
    "sit": lambda: PoseController("sit", duration=1.5),
    "zero": lambda: PoseController("zero", duration=1.0),
    "arm-track": _arm_track,
}


def make_controller(name: str, **options) -> Controller:
    """A fresh controller by name with its options; ParameterError lists the known names or options."""
    try:
        factory = CONTROLLERS[name]
    except KeyError:
        raise ParameterError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}") from None
    try:
        inspect.signature(factory).bind(**options)
    except TypeError:
        known = ", ".join(inspect.signature(factory).parameters) or "none"
        raise ParameterError(f"controller {name!r} does not take {', '.join(options)} (its options: {known})") from None
    return factory(**options)


__all__ = ["CONTROLLERS", "PoseController", "make_controller"]
