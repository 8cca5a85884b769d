"""How a spray run ends: the arm's retract to the safe position, and when the inspection
may take its frame while the arm retracts.

Declared apart from server/settings/model.py (a base of `Settings`), so the settings
of one concern live together; the environment names are the usual GLUE_APP_<NAME>.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from server.settings.section import Section


class RunEndSettings(Section):
    """The end of a spray run: the retract to the safe position, and when the inspection
    takes its frame (server/core/operations/trajectory.py and safe_position.py)."""

    title: ClassVar[str] = "The end of a run"

    retract_after_run: bool = Field(
        True,
        description="a spray run's last step moves the arm to safe_position (within the run, "
        "checked against the workspace), so the next part can be loaded; false leaves the arm "
        "over the last bead until the next run or `home`",
    )
    inspection_clearance_mm: float = Field(
        30.0,
        ge=1,
        le=2000,
        description="the inspection takes its frame once the tool is this far (x, y) outside "
        "every sprayed bead, so the arm hides no part of it; while the arm retracts, the rest "
        "of the inspection runs",
    )
