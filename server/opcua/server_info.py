"""What the OPC UA server says of itself, and how loud asyncua is in the cell's log.

BuildInfo (Server.ServerStatus.BuildInfo) names this product as its installed package
metadata says: the distribution's name and version, and as build date the time that
metadata was written (when this build was made and installed), so a client's
diagnostics show which cell server answers, not asyncua's placeholder.

asyncua logs at INFO every node it loads and every request it serves (over a thousand
lines at each start); the cell's own log is for the cell. Its loggers are set to
`opcua_log_level` (WARNING unless asked for), so asyncua's warnings and errors still
reach the log and DEBUG or INFO can be had when a protocol problem needs them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata
from typing import Final

from asyncua import Server

DISTRIBUTION: Final = "glue-cell-server"
MANUFACTURER: Final = "the glue-cell-server project"
PRODUCT_URI: Final = "urn:glue-cell-server"
ASYNCUA_LOGGER: Final = "asyncua"


@dataclass(frozen=True)
class BuildInfo:
    """The product's build as OPC UA's BuildInfoDataType holds it."""

    product_uri: str
    manufacturer: str
    product_name: str
    version: str
    build_number: str
    build_date: datetime


def build_info() -> BuildInfo:
    """This product's name, version and build date from its installed package metadata."""
    try:
        distribution = metadata.distribution(DISTRIBUTION)
    except metadata.PackageNotFoundError:  # run from a tree that was never installed
        return BuildInfo(
            PRODUCT_URI, MANUFACTURER, DISTRIBUTION, "unknown", "unknown", datetime.now(UTC)
        )
    meta = distribution.metadata
    version = distribution.version
    built = datetime.now(UTC)
    path = getattr(distribution, "_path", None)  # the metadata's directory on disk
    if path is not None:
        files = [path / "METADATA", path / "PKG-INFO"]
        stamps = [f.stat().st_mtime for f in files if f.exists()]
        if stamps:
            built = datetime.fromtimestamp(max(stamps), UTC)
    return BuildInfo(
        PRODUCT_URI,
        (meta.get_all("Author") or [MANUFACTURER])[0],
        (meta.get_all("Name") or [DISTRIBUTION])[0],
        version,
        version,
        built,
    )


async def set_build_info(server: Server) -> BuildInfo:
    """Write this product's BuildInfo into the server's status (after `Server.init`)."""
    info = build_info()
    await server.set_build_info(
        info.product_uri,
        info.manufacturer,
        info.product_name,
        info.version,
        info.build_number,
        info.build_date,
    )
    return info


def quiet_asyncua(level: str) -> None:
    """asyncua's loggers at `level` (its children inherit it)."""
    logging.getLogger(ASYNCUA_LOGGER).setLevel(level)
