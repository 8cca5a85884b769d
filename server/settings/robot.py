"""The `RobotSettings` section of the settings. The robot controller: its address ("sim"
starts the simulator on loopback) and how its link is watched.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import AliasChoices, Field

from server.settings.section import SIMULATED, Section


class RobotSettings(Section):
    """The robot controller: its address ("sim" starts the simulator on loopback) and how
    its link is watched.
    """

    title: ClassVar[str] = "Robot"

    robot_ip: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("robot_ip", "ROBOT_IP"),
        description="the robot controller's address (JSON-RPC over TCP); sim: the simulator",
    )
    robot_port: int = Field(
        30003, ge=0, le=65535, description="the robot controller's TCP port (0: any, simulator)"
    )
    robot_heartbeat_interval: float = Field(
        1.0,
        ge=0.05,
        le=60,
        description="a robot link quiet this long is asked for the position; no answer "
        "within robot_communication_timeout is a fault, in IDLE too",
    )
    robot_communication_timeout: float = Field(
        10.0, ge=0.1, le=300, description="seconds for the robot controller to answer a request"
    )

    @property
    def robot_simulated(self) -> bool:
        return self.robot_ip == SIMULATED
