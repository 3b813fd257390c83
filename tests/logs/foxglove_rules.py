"""A port of the rules of Foxglove's JSON-schema parser, for tests: the schema of a JSON channel must pass it for
Foxglove (Studio's last open-source release, ``packages/mcap-support/src/parseJsonSchema.ts``; the same in its
Lichtblick fork) to open the channel.

What the parser accepts, field by field (anything else throws, and the channel is not shown):

- the schema (and every nested object) is ``"type": "object"`` with a ``properties`` object;
- a field is ``boolean``, ``number``, ``integer``, ``string`` (no ``contentEncoding`` but base64), an object
  (recursively), an array, or a ``oneOf`` of numeric ``const`` alternatives; one type, a string, not a list;
- an array has ``items`` whose type is boolean, number, integer, string (no ``contentEncoding``) or object
  (recursively): no arrays of arrays, no ``null``.
"""

from __future__ import annotations


class Rejected(ValueError):
    pass


def parse_json_schema(schema: dict, type_name: str = "root") -> None:
    """Raise `Rejected` (naming the field) where Foxglove's parser would throw."""
    _object(schema, type_name, [])


def _object(schema: dict, type_name: str, key_path: list[str]) -> None:
    if not isinstance(schema, dict) or schema.get("type") != "object":
        raise Rejected(f'Expected "type": "object" for schema {type_name}, got {schema!r:.60}')
    props = schema.get("properties")
    if not isinstance(props, dict):  # Object.entries(undefined) throws a TypeError
        raise Rejected(f"{type_name}: an object without properties")
    for name, field in props.items():
        where = ".".join([*key_path, name])
        if isinstance(field.get("oneOf"), list):
            if all(isinstance(a.get("const"), (int, float)) for a in field["oneOf"]):
                continue
            raise Rejected(f"Unsupported type for {where}: oneOf alternatives must have number values")
        t = field.get("type")
        if t in ("boolean", "number", "integer"):
            continue
        if t == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                raise Rejected(f"Unsupported contentEncoding in {where}")
            continue
        if t == "object":
            _object(field, f"{type_name}.{name}", [*key_path, name])
            continue
        if t == "array":
            items = field.get("items")
            if not isinstance(items, dict):  # itemSchema.type of undefined throws a TypeError
                raise Rejected(f"{where}: an array without items")
            it = items.get("type")
            if it in ("boolean", "number", "integer"):
                continue
            if it == "string":
                if items.get("contentEncoding") is not None:
                    raise Rejected(f"Unsupported contentEncoding for array item {where}")
                continue
            if it == "object":
                _object(items, f"{type_name}.{name}", [*key_path, name])
                continue
            raise Rejected(f"Unsupported type {it!r} for array item {where}")
        raise Rejected(f"Unsupported type {t!r} for {where}")
