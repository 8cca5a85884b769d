"""What the cell tells a Sparkplug B host: its topics, its metrics and their types, built purely.

The edge node (`<edge_node>`, the cell id unless set) has one device, `cell`. The
node's own metrics are Sparkplug's: `bdSeq` and `Node Control/Rebirth`. The
device's metrics, each with the type a host binds to (docs/plant-integration.md,
"Sparkplug B"):

- `State` (String): the cell's own state, as GET /state names it; `State/Since`
  (DateTime) when it was entered;
- `PackML/State` (Int32): the PackML state number the cell shows on OPC UA;
- `Stop Reason/Code`, `Stop Reason/Message` (String, null when none): the
  first-out reason;
- `Run/Id`, `Run/Workpiece Id` (String, null when none): the run under way;
- `Counts/Good`, `Counts/Defective`, `Counts/Total` (Int64): the shift's
  inspected parts (GET /kpis: quality.parts_good, parts_defective, their sum);
- `OEE/OEE`, `OEE/Availability`, `OEE/Performance`, `OEE/Quality` (Double, ratios
  0 to 1, null over nothing): the shift's OEE as GET /kpis computes it;
- `Devices/Robot/Connected`, `Devices/Glue/Connected`, `Devices/Camera/Connected`
  (Boolean): each device's link as GET /health shows it;
- with commands on, `Command/<Name>` (Boolean, write true) for each command of the
  catalogue that needs no body, and `Command/Last/Name`, `Command/Last/Status`
  (Int32, the HTTP status its answer would have), `Command/Last/Message`.

Why a progress metric is not among them: DDATA goes on a change, and a run's
progress changes with every waypoint; the plant reads progress on the MQTT link's
`progress` topic. Pure: the link (`node.py`) hands in what it read.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Final

from server.commands.catalogue import CATALOGUE
from server.core.machine.transitions import Command
from server.mqtt.sparkplug.payload import DataType, Metric, Value

NAMESPACE: Final = "spBv1.0"
DEVICE: Final = "cell"
BD_SEQ: Final = "bdSeq"
REBIRTH: Final = "Node Control/Rebirth"
COMMAND_PREFIX: Final = "Command/"
LAST_NAME, LAST_STATUS, LAST_MESSAGE = (
    "Command/Last/Name",
    "Command/Last/Status",
    "Command/Last/Message",
)
SEQ_LIMIT: Final = 256  # seq runs 0..255 and wraps; bdSeq the same

DEVICE_NAMES: Final = {"robot": "Robot", "glue": "Glue", "camera": "Camera"}

# Every device metric but the commands, with its type, in the order a birth lists them.
DEVICE_METRICS: Final[dict[str, DataType]] = {
    "State": DataType.STRING,
    "State/Since": DataType.DATETIME,
    "PackML/State": DataType.INT32,
    "Stop Reason/Code": DataType.STRING,
    "Stop Reason/Message": DataType.STRING,
    "Run/Id": DataType.STRING,
    "Run/Workpiece Id": DataType.STRING,
    "Counts/Good": DataType.INT64,
    "Counts/Defective": DataType.INT64,
    "Counts/Total": DataType.INT64,
    "OEE/OEE": DataType.DOUBLE,
    "OEE/Availability": DataType.DOUBLE,
    "OEE/Performance": DataType.DOUBLE,
    "OEE/Quality": DataType.DOUBLE,
    **{f"Devices/{label}/Connected": DataType.BOOLEAN for label in DEVICE_NAMES.values()},
}
LAST_METRICS: Final[dict[str, DataType]] = {
    LAST_NAME: DataType.STRING,
    LAST_STATUS: DataType.INT32,
    LAST_MESSAGE: DataType.STRING,
}


def command_metric(command: Command) -> str:
    """`Command/<Name>`: the catalogue's word in CamelCase (calibrate-robot: CalibrateRobot)."""
    return COMMAND_PREFIX + "".join(part.capitalize() for part in command.value.split("-"))


# The commands a host may write: those whose body may be left out (a true is all a DCMD carries).
COMMAND_METRICS: Final[dict[str, Command]] = {
    command_metric(spec.command): spec.command for spec in CATALOGUE if not spec.body_required
}


@dataclass(frozen=True)
class Topics:
    """The Sparkplug topics of one edge node and its device."""

    group: str
    edge_node: str

    def node(self, kind: str) -> str:
        """NBIRTH, NDEATH, NDATA, NCMD: `spBv1.0/<group>/<kind>/<edge_node>`."""
        return f"{NAMESPACE}/{self.group}/{kind}/{self.edge_node}"

    def device(self, kind: str, device: str = DEVICE) -> str:
        """DBIRTH, DDATA, DDEATH, DCMD: `spBv1.0/<group>/<kind>/<edge_node>/<device>`."""
        return f"{self.node(kind)}/{device}"


def node_birth_metrics(bd_seq: int, now_ms: int) -> tuple[Metric, ...]:
    """NBIRTH's metrics: the session's bdSeq and the rebirth control (false)."""
    return (
        Metric(BD_SEQ, DataType.INT64, bd_seq, now_ms),
        Metric(REBIRTH, DataType.BOOLEAN, False, now_ms),
    )


def bd_seq_metric(bd_seq: int, now_ms: int) -> Metric:
    """NDEATH's one metric: the bdSeq of the NBIRTH it ends."""
    return Metric(BD_SEQ, DataType.INT64, bd_seq, now_ms)


def _ratio(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _count(value: Any) -> int:
    return int(value) if isinstance(value, int) and not isinstance(value, bool) else 0


def sample(
    snapshot: Mapping[str, Any],
    run: Mapping[str, Any] | None,
    packml_state: int,
    kpis: Mapping[str, Any] | None,
    devices: Mapping[str, Mapping[str, Any]],
) -> dict[str, Value]:
    """The device metrics' values now, from GET /state's snapshot, the run under way, the
    PackML number, GET /kpis's answer (None: not read yet, the counts 0 and OEE null)
    and GET /health's devices."""
    reason = snapshot.get("stop_reason") or {}
    operation = snapshot.get("operation") or {}
    run = run or {}
    quality = (kpis or {}).get("quality") or {}
    oee = (kpis or {}).get("oee") or {}
    good, defective = _count(quality.get("parts_good")), _count(quality.get("parts_defective"))
    values: dict[str, Value] = {
        "State": snapshot["state"],
        "State/Since": round(float(snapshot["since"]) * 1000),
        "PackML/State": packml_state,
        "Stop Reason/Code": reason.get("code"),
        "Stop Reason/Message": reason.get("message"),
        "Run/Id": run.get("run_id") or operation.get("run_id"),
        "Run/Workpiece Id": run.get("workpiece_id"),
        "Counts/Good": good,
        "Counts/Defective": defective,
        "Counts/Total": good + defective,
        "OEE/OEE": _ratio(oee.get("oee")),
        "OEE/Availability": _ratio(oee.get("availability")),
        "OEE/Performance": _ratio(oee.get("performance")),
        "OEE/Quality": _ratio(oee.get("quality")),
    }
    for name, label in DEVICE_NAMES.items():
        values[f"Devices/{label}/Connected"] = bool(devices.get(name, {}).get("connected"))
    return values


def birth_metrics(
    values: Mapping[str, Value], now_ms: int, *, commands: bool, last: Mapping[str, Value]
) -> tuple[Metric, ...]:
    """DBIRTH's metrics: every device metric with its value; with commands on, each
    command metric (false) and the last command's answer."""
    metrics = [
        Metric(name, kind, values.get(name), now_ms) for name, kind in DEVICE_METRICS.items()
    ]
    if commands:
        metrics += [Metric(name, DataType.BOOLEAN, False, now_ms) for name in COMMAND_METRICS]
        metrics += [
            Metric(name, kind, last.get(name), now_ms) for name, kind in LAST_METRICS.items()
        ]
    return tuple(metrics)


def changed_metrics(
    before: Mapping[str, Value], after: Mapping[str, Value], now_ms: int
) -> tuple[Metric, ...]:
    """DDATA's metrics: those whose value differs from what the host was last told."""
    kinds = {**DEVICE_METRICS, **LAST_METRICS}
    return tuple(
        Metric(name, kinds[name], value, now_ms)
        for name, value in after.items()
        if name not in before or before[name] != value or type(before[name]) is not type(value)
    )


def commands_in(metrics: Iterable[Metric]) -> list[tuple[str, Command]]:
    """The commands a DCMD asks for: its `Command/<Name>` metrics written true, in order;
    a metric of another name, type or value asks for nothing."""
    return [
        (metric.name, COMMAND_METRICS[metric.name])
        for metric in metrics
        if metric.name in COMMAND_METRICS
        and metric.datatype is DataType.BOOLEAN
        and metric.value is True
    ]


def rebirth_requested(metrics: Iterable[Metric]) -> bool:
    """Whether an NCMD asks for a rebirth (`Node Control/Rebirth` written true)."""
    return any(m.name == REBIRTH and m.value is True for m in metrics)
