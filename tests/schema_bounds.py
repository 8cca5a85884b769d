"""Where a JSON schema lets a number through unbounded: the tests of settings and openapi.json.

A number with no maximum is how Infinity, 1e400 and 2**64 got in; the schema is
what clients and fuzzers read, so each bound the server enforces must be in it.
"""

from __future__ import annotations

from typing import Any

NUMERIC = {"number", "integer"}


def _resolve(node: dict[str, Any], root: dict[str, Any]) -> dict[str, Any]:
    ref = node.get("$ref")
    if ref is None:
        return node
    target: Any = root
    for part in ref.removeprefix("#/").split("/"):
        target = target[part]
    return target


def unbounded_numbers(node: Any, root: dict[str, Any], where: str = "") -> list[str]:
    """Every path in `node` (refs followed through `root`) where a number lacks a bound."""
    if not isinstance(node, dict):
        return []
    if "$ref" in node:
        return unbounded_numbers(_resolve(node, root), root, where)
    found = []
    if node.get("type") in NUMERIC and "enum" not in node and "const" not in node:
        low = "minimum" in node or "exclusiveMinimum" in node
        high = "maximum" in node or "exclusiveMaximum" in node
        if not (low and high):
            found.append(where or "(root)")
    for key in ("anyOf", "oneOf", "allOf", "prefixItems"):
        for i, option in enumerate(node.get(key, [])):
            found += unbounded_numbers(option, root, f"{where}[{i}]")
    for key in ("items", "additionalProperties"):
        found += unbounded_numbers(node.get(key), root, f"{where}[]")
    for name, child in node.get("properties", {}).items():
        found += unbounded_numbers(child, root, f"{where}.{name}" if where else name)
    return found
