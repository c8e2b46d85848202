"""The one schema file for every Zenoh payload, and a small dependency-free validator for it.

``azimuthd.schema.json`` (JSON Schema 2020-12) holds one definition per topic under ``$defs``.
``validate(topic, payload)`` checks a payload against it and returns a list of error strings
(empty = valid). It implements exactly the keywords the file uses (type, const, enum, required,
properties, additionalProperties, propertyNames, anyOf, pattern, minimum, maximum,
exclusiveMaximum, items, minItems, maxItems, local $ref); the tests cross-check it against the
``jsonschema`` package on valid and invalid payloads. ``azimuthd watch`` uses it at run time so
the dashboard flags a publisher that drifted from the schema.
"""
from __future__ import annotations

import json
import math
import re
from functools import lru_cache
from pathlib import Path
from typing import Any

SCHEMA_PATH = Path(__file__).with_name("azimuthd.schema.json")


@lru_cache(maxsize=1)
def load_schema() -> dict:
    with SCHEMA_PATH.open(encoding="utf-8") as fh:
        return json.load(fh)


SCHEMA_VERSION: str = load_schema()["x-schema-version"]
TOPICS: tuple[str, ...] = tuple(load_schema()["x-topics"])

_KNOWN = {"$schema", "$id", "$ref", "$defs", "title", "description", "type", "const", "enum",
          "required", "properties", "additionalProperties", "propertyNames", "anyOf", "pattern",
          "minimum", "maximum", "exclusiveMaximum", "items", "minItems", "maxItems"}


def _type_ok(value: Any, typ: str) -> bool:
    if typ == "null":
        return value is None
    if typ == "boolean":
        return isinstance(value, bool)
    if typ == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if typ == "number":
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value))
    if typ == "string":
        return isinstance(value, str)
    if typ == "array":
        return isinstance(value, (list, tuple))
    if typ == "object":
        return isinstance(value, dict)
    raise ValueError(f"schema uses unsupported type {typ!r}")


def _resolve(ref: str) -> dict:
    if not ref.startswith("#/"):
        raise ValueError(f"only local $ref supported, got {ref!r}")
    node: Any = load_schema()
    for part in ref[2:].split("/"):
        node = node[part]
    return node


def _check(value: Any, schema: dict | bool, path: str, errors: list[str]) -> None:
    if schema is True:
        return
    if schema is False:
        errors.append(f"{path}: not allowed")
        return
    unknown = set(schema) - _KNOWN - {k for k in schema if k.startswith("x-")}
    if unknown:
        raise ValueError(f"schema at {path} uses unsupported keywords {sorted(unknown)}")
    if "$ref" in schema:
        _check(value, _resolve(schema["$ref"]), path, errors)
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_type_ok(value, t) for t in types):
            errors.append(f"{path}: expected {' or '.join(types)}, got {value!r}")
            return
    if "const" in schema and value != schema["const"]:
        errors.append(f"{path}: must be {schema['const']!r}, got {value!r}")
    if "enum" in schema and value not in schema["enum"]:
        errors.append(f"{path}: must be one of {schema['enum']}, got {value!r}")
    if "anyOf" in schema:
        if not any(not _errors(value, sub, path) for sub in schema["anyOf"]):
            errors.append(f"{path}: matches none of the allowed forms, got {value!r}")
    is_num = isinstance(value, (int, float)) and not isinstance(value, bool)
    if is_num:
        if "minimum" in schema and value < schema["minimum"]:
            errors.append(f"{path}: {value} < minimum {schema['minimum']}")
        if "maximum" in schema and value > schema["maximum"]:
            errors.append(f"{path}: {value} > maximum {schema['maximum']}")
        if "exclusiveMaximum" in schema and value >= schema["exclusiveMaximum"]:
            errors.append(f"{path}: {value} >= exclusiveMaximum {schema['exclusiveMaximum']}")
    if isinstance(value, str) and "pattern" in schema and not re.search(schema["pattern"], value):
        errors.append(f"{path}: {value!r} does not match {schema['pattern']!r}")
    if isinstance(value, (list, tuple)):
        if "minItems" in schema and len(value) < schema["minItems"]:
            errors.append(f"{path}: fewer than {schema['minItems']} items")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            errors.append(f"{path}: more than {schema['maxItems']} items")
        if "items" in schema:
            for i, item in enumerate(value):
                _check(item, schema["items"], f"{path}[{i}]", errors)
    if isinstance(value, dict):
        for key in schema.get("required", []):
            if key not in value:
                errors.append(f"{path}: missing required field {key!r}")
        props = schema.get("properties", {})
        for key, item in value.items():
            if "propertyNames" in schema:
                _check(key, schema["propertyNames"], f"{path}.{key} (name)", errors)
            if key in props:
                _check(item, props[key], f"{path}.{key}", errors)
            elif "additionalProperties" in schema:
                _check(item, schema["additionalProperties"], f"{path}.{key}", errors)


def _errors(value: Any, schema: dict | bool, path: str) -> list[str]:
    errors: list[str] = []
    _check(value, schema, path, errors)
    return errors


def validate(topic: str, payload: Any) -> list[str]:
    """Errors of ``payload`` against ``$defs/<topic>``; [] when valid. Unknown topic: ValueError."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}, expected one of {list(TOPICS)}")
    return _errors(payload, load_schema()["$defs"][topic], topic)
