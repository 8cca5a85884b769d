"""What the cell's OPC UA server says of itself (BuildInfo, timestamps) and how much of
asyncua's own logging reaches the cell's log, through asyncua's Client on loopback."""

from __future__ import annotations

import logging
from importlib import metadata
from pathlib import Path

import pytest
from asyncua import ua

from server.opcua.address_space import NAMESPACE_URI
from tests.integration.test_opcua import CELL, client, endpoint
from tests.rig import open_rig
from tests.serving import free_port


async def test_build_info_names_the_product_and_values_carry_both_timestamps(
    tmp_path: Path,
) -> None:
    port = free_port()
    async with (
        open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port)),
        client(port) as opc,
    ):
        info = await opc.get_node(ua.ObjectIds.Server_ServerStatus_BuildInfo).read_value()
        assert info.ProductName == "glue-cell-server"
        assert info.SoftwareVersion == metadata.version("glue-cell-server")
        assert info.ProductUri == "urn:glue-cell-server"
        assert info.ManufacturerName and "FreeOpcUa" not in info.ManufacturerName
        assert info.BuildDate.year >= 2024
        # The status the server reports holds the same BuildInfo as its own variable.
        status = await opc.get_node(ua.ObjectIds.Server_ServerStatus).read_value()
        assert status.BuildInfo.ProductName == "glue-cell-server"
        # A tag the cell wrote: when it became true (source) and when the server took it.
        ns = await opc.get_namespace_index(NAMESPACE_URI)
        state = opc.get_node(f"ns={ns};s={CELL}.Status.StateCurrent")
        value = await state.read_data_value(raise_on_bad_status=True)
        assert value.SourceTimestamp is not None
        assert value.ServerTimestamp is not None


class Counter(logging.Handler):
    """Counts asyncua's INFO records."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.info = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.startswith("asyncua") and record.levelno == logging.INFO:
            self.info += 1


@pytest.mark.parametrize("level", [None, "INFO"])
async def test_asyncua_logs_at_warning_unless_asked(tmp_path: Path, level: str | None) -> None:
    """The cell logs at INFO (logging_level's default); asyncua's INFO lines at start (every
    node loaded, every request served) stay out of it unless opcua_log_level asks."""
    counter = Counter()
    root = logging.getLogger()
    previous = root.level
    root.setLevel(logging.INFO)
    root.addHandler(counter)
    overrides = {"opcua_log_level": level} if level else {}
    try:
        port = free_port()
        async with (
            open_rig(tmp_path, cell_id=CELL, opcua_endpoint=endpoint(port), **overrides),
            client(port) as opc,
        ):
            await opc.get_node(ua.ObjectIds.Server_ServerStatus).read_value()
    finally:
        root.removeHandler(counter)
        root.setLevel(previous)
        logging.getLogger("asyncua").setLevel(logging.NOTSET)
    if level is None:
        assert counter.info == 0
    else:
        assert counter.info > 100  # what the default keeps out of the log
