"""Reading a recording as a Foxglove user's tools do, for the recording tests.

`decoded_messages` reads an MCAP file with the MCAP library's indexed reader and decodes the
protobuf channels with `mcap_protobuf`'s decoder (the Foxglove schemas' generated classes) and
the JSON channels with `json`. `schema_violations` checks a JSON value against the subset of
JSON Schema the recording's schemas use (type, properties, required, items, enum), so every
JSON message can be checked against the schema registered for its channel.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

_JSON_TYPES = {
    "object": dict,
    "array": list,
    "string": str,
    "boolean": bool,
    "null": type(None),
}


@dataclass
class Decoded:
    """One message as a Foxglove user's reader sees it."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema: dict[str, Any] | None
    log_time_ns: int
    sequence: int
    message: Any


def decoded_messages(path: Path) -> list[Decoded]:
    """Every message of a recording, decoded by its channel's registered schema."""
    out = []
    factory = DecoderFactory()
    schemas: dict[int, dict[str, Any]] = {}
    decoders: dict[int, Any] = {}
    with path.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            json_schema: dict[str, Any] | None = None
            if channel.message_encoding == "json":
                if schema.id not in schemas:
                    schemas[schema.id] = json.loads(schema.data)
                value: Any = json.loads(message.data)
                json_schema = schemas[schema.id]
            else:
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
                value = decoders[schema.id](message.data)
            out.append(
                Decoded(
                    channel.topic,
                    schema.name,
                    schema.encoding,
                    json_schema,
                    message.log_time,
                    message.sequence,
                    value,
                )
            )
    return out


def _is(value: Any, kind: str) -> bool:
    if kind == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "number":
        return isinstance(value, int | float) and not isinstance(value, bool)
    return isinstance(value, _JSON_TYPES[kind])


def schema_violations(value: Any, schema: dict[str, Any], where: str = "$") -> list[str]:
    """Where `value` does not follow `schema` (empty when it does)."""
    kinds = schema.get("type")
    if kinds is not None:
        kinds = [kinds] if isinstance(kinds, str) else kinds
        if not any(_is(value, k) for k in kinds):
            return [f"{where}: {value!r} is not {kinds}"]
    if "enum" in schema and value not in schema["enum"]:
        return [f"{where}: {value!r} not in {schema['enum']}"]
    problems = []
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        for key in schema.get("required", []):
            if key not in value:
                problems.append(f"{where}: {key} missing")
        for key, item in value.items():
            if key not in properties:
                problems.append(f"{where}: {key} not in the schema")
            else:
                problems += schema_violations(item, properties[key], f"{where}.{key}")
    if isinstance(value, list) and "items" in schema:
        for k, item in enumerate(value):
            problems += schema_violations(item, schema["items"], f"{where}[{k}]")
    return problems
