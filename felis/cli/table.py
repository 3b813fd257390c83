"""(being written) felis table commands."""

from __future__ import annotations


def register(sub) -> None:
    """Add this module's commands to the ``felis`` sub-commands."""
