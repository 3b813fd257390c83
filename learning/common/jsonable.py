"""JSON form of what weights and results metadata commonly hold besides plain values, for ``json.dumps``'s
``default``: numpy scalars and arrays, objects with ``to_json`` (`NetSpec`, `PaeConfig`), other dataclasses
(configs), paths."""

from __future__ import annotations

from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np


def jsonable(obj: Any) -> Any:
    """A JSON-serialisable form of ``obj``; TypeError for anything else (as ``json.dumps`` expects)."""
    if isinstance(obj, np.generic | np.ndarray):
        return obj.tolist()
    if callable(getattr(obj, "to_json", None)) and not isinstance(obj, type):
        return obj.to_json()
    if is_dataclass(obj) and not isinstance(obj, type):
        return asdict(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")
