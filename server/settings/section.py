"""The base of every settings section, and the address that means "the simulator".

A section is the settings one concern reads (the robot, the glue dispenser, MQTT,
the journal...), declared once, with the validators that need only its own fields.
`Settings` (model.py) inherits every section, so the loader, the environment names
(`GLUE_APP_<FIELD>`), the flat keys of the JSON file and `settings.robot_ip` see
one flat model; `Settings.section(RobotSettings)` hands a component its section
alone, as a frozen instance, so it can read nothing else and change nothing.

To add a section: a module under server/settings/ with one `Section` subclass (a
`title` and documented fields), and that class as one more base of `Settings`. A
plain pydantic `BaseModel` base is taken as a section too (titled from its class
name), so a section written without this base still joins the model and the docs.
"""

from __future__ import annotations

import re
from typing import ClassVar

from pydantic import BaseModel, ConfigDict

# A device address of `sim` means "start the simulator on loopback and talk to it
# through the production client", so the default run exercises the production path.
SIMULATED = "sim"


class Section(BaseModel):
    """Settings of one concern: frozen, no unknown key, no Infinity or NaN.

    The config matches `Settings`' own, so a section validated alone (a unit test, a
    tool) accepts and refuses exactly what the loader does.
    """

    model_config = ConfigDict(
        frozen=True,
        extra="forbid",
        populate_by_name=True,
        validate_default=True,
        allow_inf_nan=False,
    )

    title: ClassVar[str]
    """The section's heading in docs/settings.md."""


def title_of(section: type[BaseModel]) -> str:
    """A section's heading: its `title`, or for a plain BaseModel section its class name in
    words (`ModbusGatewaySettings` is "Modbus gateway")."""
    title = getattr(section, "title", None)
    if isinstance(title, str) and title:
        return title
    words = re.findall(r"[A-Z]+(?![a-z])|[A-Z][a-z0-9]*", section.__name__.removesuffix("Settings"))
    text = " ".join(w if w.isupper() and len(w) > 1 else w.lower() for w in words)
    return text[:1].upper() + text[1:]
