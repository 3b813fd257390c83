"""Controllers and monitors (`felis.controllers`): pure functions of HAL state and time.

They import only `felis` (and `felis.learning` for inference), never a backend, so each runs
unchanged on simulated and real robots. `make_controller` builds one by name for the CLI.
"""

from __future__ import annotations

from collections.abc import Callable

from felis.controllers.pose import PoseController
from felis.errors import ParameterError
from felis.hal import Controller

CONTROLLERS: dict[str, Callable[[], Controller]] = {
    "hold": lambda: PoseController("hold"),
    "stand": lambda: PoseController("stand", duration=0.5),
    "sit": lambda: PoseController("sit", duration=1.5),
    "zero": lambda: PoseController("zero", duration=1.0),
}


def make_controller(name: str) -> Controller:
    """A fresh controller by name; ParameterError lists the known names."""
    try:
        return CONTROLLERS[name]()
    except KeyError:
        raise ParameterError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}") from None


__all__ = ["CONTROLLERS", "PoseController", "make_controller"]
