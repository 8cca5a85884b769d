"""The workpiece library: outlines in millimetres with their spray settings.

One JSON file per workpiece (and an optional PNG thumbnail) under
`<data>/workpieces/`, each written atomically. Outlines are stored in the
robot's table frame at the pose where the part was when it was created, so a
library part can be sprayed as it lies, or matched to where it lies now.
"""

from __future__ import annotations

import builtins
import logging
import math
import re
import threading
import time
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from server.common.values import FiniteNumber, Name
from server.storage.files import read_json, write_bytes_atomic, write_json_atomic
from server.storage.permissions import private_directory
from server.vision.paths import clean_outline, fill_size, offset_polygon, simple_outline

log = logging.getLogger(__name__)

IDENTIFIER = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_ID = re.compile(IDENTIFIER)

# What a part may ask of the path planner, checked when the library is edited (422).
# Why these figures: docs/operations-guide.md ("Limits on a part's path"); the worst part
# they allow plans in under a second here (bench/planning.py), a tenth of planning_timeout.
MAX_OUTLINE_POINTS = 500  # a camera outline (0.3 mm tolerance) has tens to a few hundred
MAX_FILL_LINES = 1000  # scan lines across the part: 1 m at 1 mm, 10 m at 10 mm
MAX_FILL_STROKES = 2000  # straight fill strokes (lines × times each crosses the part / 2)
STORED_MAX_POINTS = 2000  # what a file stored before the limits may hold and still be read


class SpraySettings(BaseModel):
    """How a workpiece is sprayed."""

    model_config = ConfigDict(extra="forbid")

    outline: StrictBool = Field(True, description="spray along the outline")
    outline_offset_mm: FiniteNumber = Field(0.0, ge=-50, le=50, description=">0 outside, <0 inside")
    fill: Literal["none", "zigzag", "raster"] = "none"
    fill_spacing_mm: FiniteNumber = Field(10.0, ge=1, le=200)
    fill_angle_deg: FiniteNumber = Field(0.0, ge=-180, le=180)
    speed_mm_s: FiniteNumber = Field(100.0, gt=0, le=1000)
    flow_rate_ml_min: FiniteNumber = Field(30.0, ge=0, le=1000)


class SpraySettingsIn(SpraySettings):
    """Spray settings as an edit gives them: something to spray, as the schema says too.

    A part with no bead and no fill would fail every run with PATH_EMPTY, leaving the
    cell in ERROR for a reset. A part already stored without either is still read
    (`Workpiece` takes plain `SpraySettings`).
    """

    # The rule as a conditional, which generators that do not read it pass over: they
    # still model the settings as their typed fields (as StartRequest's rule).
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "if": {"required": ["outline"], "properties": {"outline": {"const": False}}},
            "then": {"required": ["fill"], "properties": {"fill": {"enum": ["zigzag", "raster"]}}},
        },
    )

    @model_validator(mode="after")
    def _something_to_spray(self) -> SpraySettingsIn:
        if not self.outline and self.fill == "none":
            raise ValueError("nothing to spray: outline is false and fill is none")
        return self


# Table-frame millimetres: far beyond any table, so only a typo or garbage is refused.
OUTLINE_LIMIT_MM = 5000
Coordinate = Annotated[FiniteNumber, Field(ge=-OUTLINE_LIMIT_MM, le=OUTLINE_LIMIT_MM)]
Point = tuple[Coordinate, Coordinate]


class WorkpieceIn(BaseModel):
    """What a client sends to create or replace a workpiece."""

    model_config = ConfigDict(extra="forbid")

    # Why a ClassVar: a stored entry keeps being readable under tighter edit limits.
    edit_limits: ClassVar[bool] = True

    name: Name
    outline_mm: list[Point] = Field(
        min_length=3,
        max_length=MAX_OUTLINE_POINTS,
        description=f"(x, y) mm in the table frame, each within ±{OUTLINE_LIMIT_MM} mm",
    )
    spray: SpraySettingsIn = Field(default_factory=SpraySettingsIn)

    @field_validator("outline_mm")
    @classmethod
    def _has_an_inside(cls, outline: list[Point]) -> list[Point]:
        """Three points on a line, or one point thrice, are no part: refused here, where the
        run would fail with PATH_INVALID and leave the cell in ERROR for a reset."""
        if cls.edit_limits:
            clean_outline(outline)
        return outline

    @field_validator("spray")
    @classmethod
    def _fill_plannable(cls, spray: SpraySettings, info: ValidationInfo) -> SpraySettings:
        """Refuse a fill too fine for the part: it would take too long to plan and spray.

        The 800-point outline with a 1 mm fill kept planning threads busy for minutes; the
        count here costs a millisecond and names the spacing that would be accepted.
        """
        outline = info.data.get("outline_mm")
        if not cls.edit_limits or spray.fill == "none" or outline is None:
            return spray
        try:
            lines, strokes = fill_size(
                np.asarray(outline, dtype=np.float64),
                spray.fill_spacing_mm,
                spray.fill_angle_deg,
                max_lines=MAX_FILL_LINES,
            )
        except ValueError:
            return spray  # a degenerate outline, refused as outline_mm
        if strokes is None:
            wanted = math.ceil(spray.fill_spacing_mm * lines / MAX_FILL_LINES * 10) / 10
            raise ValueError(
                f"fill_spacing_mm {spray.fill_spacing_mm:g} gives {lines} fill lines across "
                f"this outline, at most {MAX_FILL_LINES}: use a spacing of at least "
                f"{wanted:.1f} mm"
            )
        if strokes > MAX_FILL_STROKES:
            wanted = math.ceil(spray.fill_spacing_mm * strokes / MAX_FILL_STROKES * 10) / 10
            raise ValueError(
                f"fill_spacing_mm {spray.fill_spacing_mm:g} gives {strokes} fill strokes on "
                f"this outline, at most {MAX_FILL_STROKES}: use a spacing of about "
                f"{wanted:.1f} mm or more, or a simpler outline"
            )
        return spray

    def path_problem(self) -> tuple[str, str] | None:
        """What the path planner would refuse of this part, as (field, reason); None if nothing.

        The checks validation leaves out because they cost: whether the outline crosses
        itself, and whether the bead's offset leaves an outline (up to half a second for
        the largest part allowed). So call it off the event loop.
        """
        try:
            outline = simple_outline(self.outline_mm)
        except ValueError as exc:
            return "outline_mm", str(exc)
        try:
            offset_polygon(outline, self.spray.outline_offset_mm, checkpoint=_give_way)
        except ValueError as exc:
            return "spray.outline_offset_mm", str(exc)
        return None


def _give_way() -> None:
    """The offset's checkpoint: lets the event loop have the interpreter between steps."""
    time.sleep(0)


class Workpiece(WorkpieceIn):
    """A library entry."""

    edit_limits: ClassVar[bool] = False
    # Why looser than WorkpieceIn: a file stored before a limit was tightened stays readable.
    name: str = Field(min_length=1, max_length=100)
    outline_mm: list[Point] = Field(min_length=3, max_length=STORED_MAX_POINTS)
    spray: SpraySettings = Field(default_factory=SpraySettings)  # type: ignore[assignment]
    id: str = Field(pattern=IDENTIFIER)
    created_at: float
    updated_at: float
    source: Literal["camera", "api"] = "api"
    has_thumbnail: bool = False


class DamagedWorkpiece(BaseModel):
    """A library file that cannot be read as a part, and why."""

    id: str
    reason: str


class DamagedEntry(ValueError):
    """The part's file exists but cannot be read (truncated, not JSON, invalid)."""

    def __init__(self, workpiece_id: str, reason: str) -> None:
        self.workpiece_id = workpiece_id
        self.reason = reason
        super().__init__(f"workpiece {workpiece_id!r} is damaged: {reason}")


def _reason(exc: Exception) -> str:
    """One line a technician can read: the JSON error, or the first invalid field."""
    if isinstance(exc, ValidationError):
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "document"
        return f"{where}: {first['msg']} ({exc.error_count()} problem(s))"
    if exc.__cause__ is not None:  # read_json: the decoder's own words
        return f"not valid JSON: {exc.__cause__}"
    return str(exc)


class WorkpieceLibrary:
    """CRUD over the workpiece files; safe to call from worker threads."""

    def __init__(self, data_path: Path) -> None:
        self.directory = data_path / "workpieces"
        private_directory(self.directory)
        self._lock = threading.RLock()  # create() allocates an id and writes under one hold

    def _path(self, workpiece_id: str) -> Path:
        if not _ID.match(workpiece_id):
            raise KeyError(workpiece_id)
        return self.directory / f"{workpiece_id}.json"

    def thumbnail_path(self, workpiece_id: str) -> Path:
        return self._path(workpiece_id).with_suffix(".png")

    def list(self) -> list[Workpiece]:
        """Every readable part; a damaged file is left out (see `damaged`), never fatal."""
        return self.survey()[0]

    def damaged(self) -> builtins.list[DamagedWorkpiece]:
        """The files that cannot be read as a part, each with the reason."""
        return self.survey()[1]

    def survey(self) -> tuple[builtins.list[Workpiece], builtins.list[DamagedWorkpiece]]:
        """The readable parts and the damaged files, in one pass over the directory.

        Why not fail: one truncated file (a full disk, a hand edit) must not stop
        the server or hide the other parts; it is listed with its reason until
        PUT repairs it or DELETE removes it.
        """
        items: list[Workpiece] = []
        damaged: list[DamagedWorkpiece] = []
        for path in sorted(self.directory.glob("*.json")):
            try:
                items.append(Workpiece.model_validate(read_json(path)))
            except (ValueError, ValidationError) as exc:
                reason = _reason(exc)
                log.error("workpiece file %s is damaged, left out: %s", path, reason)
                damaged.append(DamagedWorkpiece(id=path.stem, reason=reason))
        return items, damaged

    def exists(self, workpiece_id: str) -> bool:
        """Whether the library holds `workpiece_id` (a stat, no read: cheap enough to ask often)."""
        try:
            return self._path(workpiece_id).exists()
        except KeyError:
            return False

    def is_empty(self) -> bool:
        """No readable part: a library of damaged files matches nothing.

        Reads files only until the first good one: this is asked before every
        start with contour matching, on the event loop.
        """
        for path in self.directory.glob("*.json"):
            try:
                Workpiece.model_validate(read_json(path))
            except (ValueError, ValidationError):
                continue
            return False
        return True

    def get(self, workpiece_id: str) -> Workpiece:
        """The workpiece; KeyError when there is none, DamagedEntry when its file is unreadable."""
        path = self._path(workpiece_id)
        try:
            document = read_json(path)
            if document is None:
                raise KeyError(workpiece_id)
            return Workpiece.model_validate(document)
        except (ValueError, ValidationError) as exc:
            raise DamagedEntry(workpiece_id, _reason(exc)) from exc

    def new_id(self) -> str:
        with self._lock:
            existing = {p.stem for p in self.directory.glob("*.json")}
            number = len(existing) + 1
            while f"wp-{number:04d}" in existing:
                number += 1
            return f"wp-{number:04d}"

    def put(
        self,
        workpiece_id: str,
        data: WorkpieceIn,
        *,
        source: str = "api",
        thumbnail_png: bytes | None = None,
    ) -> Workpiece:
        """Create or replace; keeps created_at of an existing entry; repairs a damaged one."""
        path = self._path(workpiece_id)
        now = time.time()
        with self._lock:
            try:
                created = self.get(workpiece_id).created_at
            except (KeyError, DamagedEntry):
                created = now
            if thumbnail_png is not None:
                write_bytes_atomic(self.thumbnail_path(workpiece_id), thumbnail_png)
            workpiece = Workpiece(
                **data.model_dump(),
                id=workpiece_id,
                created_at=created,
                updated_at=now,
                source=source,
                has_thumbnail=self.thumbnail_path(workpiece_id).exists(),
            )
            write_json_atomic(path, workpiece.model_dump(mode="json"))
        return workpiece

    def create(
        self,
        data: WorkpieceIn,
        *,
        workpiece_id: str | None = None,
        source: str = "api",
        thumbnail_png: bytes | None = None,
    ) -> Workpiece:
        """Store a new part under `workpiece_id` or the next free wp-NNNN id; never replaces.

        Raises FileExistsError when `workpiece_id` is taken: changing a part is
        `put` (PUT /workpieces/{id}, maintenance), never a creation.
        """
        with self._lock:
            if workpiece_id is not None and self.exists(workpiece_id):
                raise FileExistsError(workpiece_id)
            chosen = workpiece_id or self.new_id()
            return self.put(chosen, data, source=source, thumbnail_png=thumbnail_png)

    def delete(self, workpiece_id: str) -> None:
        """Remove the entry and its thumbnail; KeyError if there is none."""
        path = self._path(workpiece_id)
        with self._lock:
            if not path.exists():
                raise KeyError(workpiece_id)
            path.unlink()
            self.thumbnail_path(workpiece_id).unlink(missing_ok=True)
