"""JSON schemas for felis's own JSON channels, built to Foxglove's rules: one type per field, ``properties`` on every
object, ``items`` on every array, no arrays of arrays (the rules of Foxglove's open-source JSON-schema parser;
`schema_of` builds a schema from example values), and the JSON text those channels carry (`jsonable`)."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

# ---------------------------------------------------------------------------------------------
# JSON schemas (Foxglove's rules: one type per field, properties on objects, items on arrays)

_NUM = {"type": "number"}
_XYZ = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}

FAULTS_SCHEMA = {"type": "object", "title": "felis.Faults", "properties": {
    "hardware": {"type": "array", "items": {"type": "integer"}, "description": "hardware error bits per joint"},
    "comm_errors": {"type": "integer"},
    "stale": {"type": "array", "items": {"type": "boolean"}, "description": "joints whose reading is old"}}}


def schema_of(value: Any, title: str | None = None) -> dict:
    """A JSON schema of ``value`` (already made JSON-able by `jsonable`) that Foxglove's parser accepts."""
    if isinstance(value, bool):
        out: dict = {"type": "boolean"}
    elif isinstance(value, int):
        out = {"type": "integer"}
    elif isinstance(value, float) or value is None:
        out = {"type": "number"}
    elif isinstance(value, str):
        out = {"type": "string"}
    elif isinstance(value, dict):
        out = {"type": "object", "properties": {k: schema_of(v) for k, v in value.items()}}
    elif isinstance(value, list):
        out = {"type": "array", "items": _merge([schema_of(v) for v in value if v is not None])}
    else:
        out = {"type": "string"}
    if title is not None:
        out["title"] = title
    return out


def _merge(schemas: list[dict]) -> dict:
    """One schema for a list's items: the first item's type; objects merge their properties."""
    if not schemas:
        return {"type": "number"}
    first = schemas[0]
    if first["type"] == "number" and any(s["type"] == "integer" for s in schemas):
        return first
    if first["type"] == "integer" and any(s["type"] == "number" for s in schemas):
        return {"type": "number"}
    if first["type"] != "object":
        return first
    props: dict = {}
    for s in schemas:
        if s["type"] == "object":
            for k, v in s["properties"].items():
                props.setdefault(k, v)
    return {"type": "object", "properties": props}


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    return str(obj)


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values that fit one schema: numpy → Python, NaN/inf → None, keys → str; None values
    in objects are left out (Foxglove has no null type); an array of arrays becomes an array of objects
    ``{"items": […]}`` (Foxglove's parser takes no nested arrays)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, dict):
        out = {str(k): jsonable(v) for k, v in obj.items()}
        return {k: v for k, v in out.items() if v is not None}
    if isinstance(obj, (list, tuple, set, frozenset, np.ndarray)):
        items = [jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
        if any(isinstance(v, list) for v in items):
            items = [{"items": v} if isinstance(v, list) else v for v in items]
        return items
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    return jsonable(_default(obj))


def _text(msg: Any) -> bytes:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


