"""The `CameraSettings` section of the settings. The camera ("sim" is the simulated
camera), its frame timeout and its set-up view.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import AliasChoices, Field

from server.settings.section import SIMULATED, Section


class CameraSettings(Section):
    """The camera ("sim" is the simulated camera), its frame timeout and its set-up view."""

    title: ClassVar[str] = "Camera"

    vision_camera_id: str = Field(
        SIMULATED,
        validation_alias=AliasChoices("vision_camera_id", "VISION_CAMERA_ID"),
        description="the camera: an OpenCV index or URL; sim: the simulated camera",
    )
    vision_processing_timeout: float = Field(
        5.0, ge=0.1, le=300, description="seconds for the camera to deliver a frame"
    )
    camera_preview_fps: float = Field(
        5.0,
        ge=0.5,
        le=15,
        description="the camera set-up view (/camera/preview/ws) sends at most this many "
        "annotated frames a second, whatever the number of clients; each costs a capture, "
        "a marker detection and a JPEG, off the event loop",
    )
    camera_preview_clients: int = Field(
        2,
        ge=1,
        le=10,
        description="at most this many clients watch the camera set-up view at once; one "
        "more is refused",
    )

    @property
    def camera_simulated(self) -> bool:
        return self.vision_camera_id == SIMULATED
