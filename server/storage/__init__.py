"""What the cell keeps on disk under the data directory: calibrations, the marker layout
being taught, the workpiece library, the runs' inspection images and the settings
changed at runtime."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from server.storage.calibration import CalibrationStore
from server.storage.inspection_images import InspectionImages
from server.storage.marker_layout import MarkerLayoutStore
from server.storage.permissions import private_directory
from server.storage.runtime_settings import RuntimeSettingsStore
from server.storage.workpieces import WorkpieceLibrary


@dataclass
class CellStores:
    """Everything persistent an operation may read or write."""

    calibration: CalibrationStore
    workpieces: WorkpieceLibrary
    markers: MarkerLayoutStore
    inspection_images: InspectionImages | None = None
    runtime_settings: RuntimeSettingsStore | None = None

    @classmethod
    def open(cls, data_path: Path) -> CellStores:
        private_directory(data_path)
        return cls(
            CalibrationStore(data_path),
            WorkpieceLibrary(data_path),
            MarkerLayoutStore(data_path),
            InspectionImages(data_path),
            RuntimeSettingsStore(data_path),
        )
