"""Moved to server.storage.journal; this shim goes once nothing imports it from here."""

from server.storage.journal import *  # noqa: F403
from server.storage.journal import Journal, Record  # noqa: F401
