"""OPC 30050 (PackML) v1.1's published model, read for the tests (tests/reference/packml/).

The product builds its address space itself; these helpers give the tests the
standard's own view to check it against: the types and their members with modelling
rules, type definitions and data types; the states with their StateNumbers; and the
transitions of the three nested state machines, flattened to the 17 states.
"""

from __future__ import annotations

import csv
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cache
from pathlib import Path

DIRECTORY = Path(__file__).resolve().parent / "reference" / "packml"
NODESET = DIRECTORY / "Opc.Ua.PackML.NodeSet2.xml"
NODE_IDS = DIRECTORY / "PackML.NodeIds.csv"
_UA = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
MANDATORY = "i=78"


@dataclass(frozen=True)
class Declared:
    """A member a type declares, as the NodeSet gives it."""

    name: str  # browse name without its namespace prefix
    node_id: str  # "ns=1;i=200"
    node_class: str  # "Object", "Variable", "Method"
    type_definition: str | None  # "i=63", "ns=1;i=4"
    data_type: str | None  # alias or id, as written ("Int32", "ns=1;i=15")
    reference: str  # HasComponent, HasProperty, HasStopReason...
    mandatory: bool


@cache
def _document() -> tuple[dict[str, ET.Element], dict[str, str]]:
    root = ET.parse(NODESET).getroot()
    nodes = {node.get("NodeId", ""): node for node in root if node.get("NodeId")}
    aliases = {a.get("Alias", ""): a.text or "" for a in root.iter(f"{_UA}Alias")}
    return nodes, aliases


def _references(node: ET.Element) -> list[tuple[str, bool, str]]:
    found = node.find(f"{_UA}References")
    return [
        (r.get("ReferenceType", ""), r.get("IsForward", "true") != "false", r.text or "")
        for r in (found if found is not None else [])
    ]


def bare(name: str) -> str:
    return name.split(":", 1)[1] if ":" in name else name


def resolve(alias: str) -> str:
    """A DataType as written in the NodeSet, as a node id string."""
    return _document()[1].get(alias, alias)


def type_id(name: str) -> str:
    """The node id of the type (object, data or reference type) called `name`."""
    nodes, _ = _document()
    for node_id, node in nodes.items():
        if node.tag.endswith("Type") and bare(node.get("BrowseName", "")) == name:
            return node_id
    raise KeyError(name)


def members(type_name: str) -> list[Declared]:
    """What the type declares (not its supertypes'), with its modelling rule."""
    nodes, _ = _document()
    declared = []
    for kind, forward, target in _references(nodes[type_id(type_name)]):
        child = nodes.get(target)
        if not forward or child is None or kind in ("HasSubtype", "HasModellingRule"):
            continue
        refs = _references(child)
        rules = [t for k, f, t in refs if k == "HasModellingRule" and f]
        definitions = [t for k, f, t in refs if k == "HasTypeDefinition" and f]
        declared.append(
            Declared(
                bare(child.get("BrowseName", "")),
                target,
                child.tag.removeprefix(_UA).removeprefix("UA"),
                definitions[0] if definitions else None,
                child.get("DataType"),
                kind,
                MANDATORY in rules,
            )
        )
    return declared


def state_numbers() -> dict[str, int]:
    """Each state's browse name and StateNumber (Running and Cleared included)."""
    nodes, _ = _document()
    numbers = {}
    for node in nodes.values():
        if node.get("BrowseName") != "StateNumber":
            continue
        owner = nodes[node.get("ParentNodeId", "")]
        value = node.find(f"{_UA}Value")
        numbers[bare(owner.get("BrowseName", ""))] = int("".join(value.itertext()).strip())
    return numbers


def state_number_ids() -> dict[int, int]:
    """Each state object's numeric id → its StateNumber property's numeric id."""
    nodes, _ = _document()
    return {
        int(node.get("ParentNodeId", "").split("i=")[1]): int(node_id.split("i=")[1])
        for node_id, node in nodes.items()
        if node.get("BrowseName") == "StateNumber"
    }


def state_ids() -> dict[str, str]:
    """Each state object's node id, by browse name."""
    nodes, _ = _document()
    return {
        bare(node.get("BrowseName", "")): node_id
        for node_id, node in nodes.items()
        if any(k == "HasTypeDefinition" and t == "i=2307" for k, _, t in _references(node))
    }


def _transitions() -> list[tuple[str, str]]:
    """Every transition object's (from, to) state names, as the NodeSet links them."""
    nodes, _ = _document()
    pairs = []
    for node in nodes.values():
        refs = _references(node)
        if not any(k == "HasTypeDefinition" and t == "i=2310" for k, _, t in refs):
            continue
        source = [t for k, f, t in refs if k == "FromState" and f]
        target = [t for k, f, t in refs if k == "ToState" and f]
        name = lambda i: bare(nodes[i].get("BrowseName", ""))  # noqa: E731
        pairs.append((name(source[0]), name(target[0])))
    return pairs


# A super-state is entered at its first sub-state (OPC 30050 6.2: Running begins in
# Resetting, Cleared in Clearing), and a transition out of it leaves any sub-state.
ENTERED_AT = {"Running": "Resetting", "Cleared": "Clearing"}
SUB_STATES = {
    "Running": {
        "Resetting", "Idle", "Starting", "Execute", "Holding", "Held", "Unholding",
        "Suspending", "Suspended", "Unsuspending", "Completing", "Complete",
    },
}  # fmt: skip
SUB_STATES["Cleared"] = SUB_STATES["Running"] | {"Stopped", "Stopping", "Clearing"}


@cache
def allowed() -> frozenset[tuple[int, int]]:
    """The standard's transitions between the 17 states, as StateNumber pairs."""
    numbers = state_numbers()
    pairs = set()
    for source, target in _transitions():
        target = ENTERED_AT.get(target, target)
        for each in SUB_STATES.get(source, {source}):
            pairs.add((numbers[each], numbers[target]))
    return frozenset(pairs)


def node_ids() -> dict[str, int]:
    """NodeIds.csv: symbolic name → numeric id."""
    with NODE_IDS.open(newline="") as handle:
        return {row[0]: int(row[1]) for row in csv.reader(handle) if row}
