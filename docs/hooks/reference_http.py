"""The HTTP reference page, written from the app's OpenAPI document.

Every route has a `## METHOD /path` heading (anchor e.g. `#post-api-retrieve`) with its request
body's fields (type, bounds, default) and its answers by status; the schemas of those answers
follow under `## Schemas` (anchor e.g. `#schema-retrieveresponse`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from typing import Any

from reference_text import cell, text

METHODS = ("get", "put", "post", "delete", "patch", "head", "options")

HEADER = """# HTTP API

What `links serve` answers. This page is written from the app's OpenAPI document each time the
site is built; a running server gives the same document at `GET /openapi.json`.
"""


def routes(document: dict[str, Any]) -> dict[str, set[str]]:
    """Each path of `document` and the HTTP methods (upper case) it answers."""
    return {
        path: {method.upper() for method in item if method in METHODS}
        for path, item in document["paths"].items()
    }


def route_anchor(method: str, path: str) -> str:
    """The anchor of a route's section: `post-api-retrieve` for POST /api/retrieve."""
    words = re.findall(r"[a-z0-9]+", path.lower())
    return "-".join([method.lower(), *words]) if words else f"{method.lower()}-root"


def schema_anchor(name: str) -> str:
    """The anchor of a schema's section: `schema-retrieveresponse`."""
    return "schema-" + re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def _number(value: float | int) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e6:
        value = int(value)
    return format(value, "g") if isinstance(value, float) else str(value)


def _bounds(schema: dict[str, Any]) -> str:
    low = schema.get("minimum")
    exclusive_low = schema.get("exclusiveMinimum")
    high = schema.get("maximum")
    exclusive_high = schema.get("exclusiveMaximum")
    parts = []
    if low is not None:
        parts.append(f"≥ {_number(low)}")
    if exclusive_low is not None:
        parts.append(f"> {_number(exclusive_low)}")
    if high is not None:
        parts.append(f"≤ {_number(high)}")
    if exclusive_high is not None:
        parts.append(f"< {_number(exclusive_high)}")
    return f" ({', '.join(parts)})" if parts else ""


def _length(schema: dict[str, Any]) -> str:
    low, high = schema.get("minItems"), schema.get("maxItems")
    if low is not None and low == high:
        return f"[{low}]"
    if low is None and high is None:
        return ""
    return f"[{low or 0}..{high if high is not None else ''}]"


def _literal(value: Any) -> str:
    return json.dumps(value)


def type_text(schema: dict[str, Any], anchors: dict[str, str]) -> str:
    """A JSON schema in a few words: `list[3..10000] of list[2] of number (≥ -1e+12, ≤ 1e+12)`;
    a `$ref` links to its anchor in `anchors` (schema name to anchor)."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{anchors[name]})" if name in anchors else name
    if "anyOf" in schema:
        return " or ".join(type_text(option, anchors) for option in schema["anyOf"])
    if "const" in schema:
        return _literal(schema["const"])
    if "enum" in schema:
        return " or ".join(_literal(value) for value in schema["enum"])
    kind = schema.get("type")
    if kind == "array":
        items = schema.get("items")
        inner = f" of {type_text(items, anchors)}" if items else ""
        return f"list{_length(schema)}{inner}"
    if kind is None:
        return "any"
    return f"{kind}{_bounds(schema)}"


def _fields(schema: dict[str, Any], anchors: dict[str, str]) -> Iterator[str]:
    properties = schema.get("properties", {})
    if not properties:
        return
    required = set(schema.get("required", ()))
    yield "| field | type and bounds | required | default | meaning |"
    yield "|---|---|---|---|---|"
    for name, field in properties.items():
        default = _literal(field["default"]) if "default" in field else ""
        yield (
            f"| `{name}` | {cell(type_text(field, anchors))} | "
            f"{'yes' if name in required else 'no'} | {f'`{default}`' if default else ''} | "
            f"{text(field.get('description', ''))} |"
        )
    yield ""


def _resolve(document: dict[str, Any], schema: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """(name, schema) of a body schema that may be a `$ref` into the components."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return name, document["components"]["schemas"][name]
    return schema.get("title", ""), schema


def _request_body_names(document: dict[str, Any]) -> set[str]:
    """Schemas used only as request bodies: their fields are shown with their routes."""
    names = set()
    for item in document["paths"].values():
        for method, operation in item.items():
            if method in METHODS and "requestBody" in operation:
                for media in operation["requestBody"].get("content", {}).values():
                    if "$ref" in media.get("schema", {}):
                        names.add(media["schema"]["$ref"].rsplit("/", 1)[-1])
    return names


def _route(
    document: dict[str, Any], method: str, path: str, operation: dict[str, Any], anchors: dict
) -> Iterator[str]:
    yield f"## {method.upper()} {path} {{#{route_anchor(method, path)}}}"
    yield ""
    description = operation.get("description") or operation.get("summary", "")
    if description:
        yield text(description)
        yield ""
    parameters = operation.get("parameters", [])
    if parameters:
        yield "Parameters:"
        yield ""
        yield "| name | in | type | required | meaning |"
        yield "|---|---|---|---|---|"
        for parameter in parameters:
            yield (
                f"| `{parameter['name']}` | {parameter['in']} | "
                f"{cell(type_text(parameter.get('schema', {}), anchors))} | "
                f"{'yes' if parameter.get('required') else 'no'} | "
                f"{text(parameter.get('description', ''))} |"
            )
        yield ""
    body = operation.get("requestBody")
    if body:
        for media, content in body.get("content", {}).items():
            name, schema = _resolve(document, content.get("schema", {}))
            yield f"Request body (`{media}`, {name}):"
            yield ""
            if schema.get("description"):
                yield text(schema["description"])
                yield ""
            yield from _fields(schema, anchors)
    yield "Answers:"
    yield ""
    yield "| status | meaning | body |"
    yield "|---|---|---|"
    for status, answer in sorted(operation.get("responses", {}).items()):
        bodies = []
        for media, content in answer.get("content", {}).items():
            schema = content.get("schema")
            shown = f"`{media}`"
            if schema and "$ref" in schema:
                shown += f" {type_text(schema, anchors)}"
            elif schema and schema.get("type"):
                shown += f" {type_text(schema, anchors)}"
            bodies.append(shown)
        yield f"| {status} | {text(answer.get('description', ''))} | {cell(', '.join(bodies))} |"
    yield ""


def http_page(document: dict[str, Any]) -> str:
    """The page's Markdown: every route of the OpenAPI `document`, then its schemas."""
    schemas = document.get("components", {}).get("schemas", {})
    inline = _request_body_names(document)
    listed = [name for name in schemas if name not in inline]
    anchors = {name: schema_anchor(name) for name in listed}
    lines = [HEADER]
    info = document.get("info", {}).get("description")
    if info:
        lines += [text(info), ""]
    lines += ["| route | what it does |", "|---|---|"]
    for path, item in document["paths"].items():
        for method, operation in item.items():
            if method in METHODS:
                summary = " ".join((operation.get("description") or "").split())
                summary = re.split(r"; |\. ", summary)[0].rstrip(".")
                lines.append(
                    f"| [{method.upper()} `{path}`](#{route_anchor(method, path)}) | "
                    f"{text(summary)} |"
                )
    lines.append("")
    for path, item in document["paths"].items():
        for method, operation in item.items():
            if method in METHODS:
                lines.extend(_route(document, method, path, operation, anchors))
    if listed:
        lines += ["## Schemas", ""]
        for name in listed:
            schema = schemas[name]
            lines += [f"### {name} {{#{anchors[name]}}}", ""]
            if schema.get("description"):
                lines += [text(schema["description"]), ""]
            lines.extend(_fields(schema, anchors))
    return "\n".join(lines)
