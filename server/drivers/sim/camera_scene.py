"""What the simulated cell camera sees on the work table, with exact ground truth.

The table (z = 0 in the robot base frame) carries the nine ArUco calibration markers and any
workpieces. A frame is rendered the way a real camera forms it, so that vision code tested
against it earns its accuracy claims honestly:

1. the table content is drawn *in table coordinates* at `TABLE_MM_PER_PX` (0.25 mm, about 2.6
   times finer than a camera pixel), every edge with its exact area coverage;
2. it is band-limited by the camera pixel's footprint plus a slightly soft lens;
3. for every camera pixel the table point it sees is computed through the exact camera model
   (undistortion + ray/plane intersection) and the table image is sampled there with
   `cv2.remap` — so geometry is exact to ~0.01 px, and anti-aliasing follows from steps 1-2;
4. vignetting, a lighting gradient and Gaussian sensor noise are applied per frame;
5. the glue bead dispensed, if any (`Scene.bead`, see `camera_bead.py`), over the parts in
   the same way (drawn in table coordinates, then through the camera);
6. optionally (`Scene.degradations`, off by default) what a real table adds: residual lens
   distortion, blur, uneven light, more noise, JPEG, marker sheets printed off scale
   (`camera_degradations.py`).

Steps 1-3 only change when the scene changes, so they are cached, as the remapped 8-bit
frame (6 MB; lit, in float, it would be 25 MB): a warm frame costs its light and noise
only. The table with its markers is cached on its own (~45 MB); the parts are drawn onto a
copy of it whenever the frame itself must be drawn again (~12 ms a part), so a bead that
grows from frame to frame costs a copy, the parts, its own drawing and the remap.
Each cache holds one entry, the table the camera looks at now: the image process keeps no
second table it is not looking at.
Nothing here does I/O; `server.drivers.camera.SimulatedCamera` wraps it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.drivers.sim.camera_bead import BEAD_BGR, BeadLayer, bead_coverage
from server.drivers.sim.camera_chessboard import (
    DEFAULT_CHESSBOARD,
    BoardPose,
    Chessboard,
    chessboard_corner_pixels,
    clear_chessboard_cache,
    default_chessboard_poses,
    render_chessboard_view,
)
from server.drivers.sim.camera_degradations import Degradations
from server.drivers.sim.camera_model import (
    DEFAULT_CAMERA_MODEL,
    CameraModel,
    expose,
    footprint_blur_sigma_px,
    lighting_gain,
    normalised_pixel_grid,
)
from server.drivers.sim.camera_workpieces import (
    WORKPIECE_SHAPES,
    Workpiece,
    WorkpieceShape,
    polygon_area_centroid,
)
from server.settings.model import DEFAULT_MARKER_POSITIONS_MM

logger = logging.getLogger(__name__)

__all__ = [
    "ARUCO_DICTIONARY_ID",
    "ARUCO_DICTIONARY_NAME",
    "DEFAULT_CAMERA_MODEL",
    "DEFAULT_CHESSBOARD",
    "DEFAULT_MARKER_SIZE_MM",
    "TABLE_MM_PER_PX",
    "WORKPIECE_SHAPES",
    "BoardPose",
    "CameraModel",
    "Chessboard",
    "Degradations",
    "Scene",
    "Workpiece",
    "WorkpieceShape",
    "aruco_dictionary",
    "chessboard_corner_pixels",
    "clear_render_caches",
    "default_chessboard_poses",
    "draw_table_ahead",
    "marker_centre_pixels",
    "marker_corner_pixels",
    "marker_corners_mm",
    "polygon_area_centroid",
    "polygon_coverage",
    "release_chessboard_state",
    "render_chessboard_view",
    "render_table",
    "workpiece_outline_pixels",
]

# The cell's markers: DICT_4X4_50 has the largest cells for a given printed size (6×6 cells
# with the black border), which keeps 30 mm markers about 8 px per cell at 900 mm.
ARUCO_DICTIONARY_ID = cv2.aruco.DICT_4X4_50
ARUCO_DICTIONARY_NAME = "DICT_4X4_50"
DEFAULT_MARKER_SIZE_MM = 30.0  # side of the black square, as printed

TABLE_MM_PER_PX = 0.25  # resolution of the internal table image

# Reflectances in grey levels (before lighting): matte marker paper and toner.
PAPER_BGR = (236.0, 236.0, 232.0)
INK_BGR = (24.0, 24.0, 26.0)


def aruco_dictionary() -> cv2.aruco.Dictionary:
    """The dictionary the cell's markers are printed from."""
    return cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY_ID)


@dataclass
class Scene:
    """The table as the camera should see it: markers, workpieces, table and light.

    Marker i (0..8) sits with its centre at `marker_positions_mm[i]`, printed square to the
    robot axes: the top row of the marker image points to -x, so it reads upright in the
    camera image. Each has a white quiet zone of `quiet_zone_mm` around the black square.
    Mutable on purpose (tests and the simulated camera move workpieces); renders snapshot it.
    """

    marker_positions_mm: list[tuple[float, float]] = field(
        default_factory=lambda: list(DEFAULT_MARKER_POSITIONS_MM)
    )
    marker_size_mm: float = DEFAULT_MARKER_SIZE_MM
    quiet_zone_mm: float = 7.5
    workpieces: list[Workpiece] = field(default_factory=list)
    table_bgr: tuple[float, float, float] = (62.0, 66.0, 70.0)
    table_texture: float = 4.0  # amplitude (grey levels) of the table's mottling
    noise_sigma: float = 2.0  # sensor noise, grey levels
    vignetting: float = 0.12  # fractional brightness drop in the image corners
    light_gradient: float = 0.05  # fractional brightness change from left to right
    # A camera set up badly, for the set-up view's figures: a lens out of focus (Gaussian
    # blur, px) and the exposure (gain on the light reaching the sensor, 1 = as set up).
    defocus_px: float = 0.0
    exposure: float = 1.0
    seed: int = 0  # table texture, and sensor noise when no rng is given
    # What a real table adds to the frame (none by default): see camera_degradations.py.
    degradations: Degradations | None = None
    # The glue dispensed on the parts (camera_bead.py); None: no bead.
    bead: BeadLayer | None = None

    @property
    def printed_marker_size_mm(self) -> float:
        """The black square's side as printed: `marker_size_mm` times any print scale."""
        scale = self.degradations.print_scale if self.degradations else 1.0
        return self.marker_size_mm * scale

    @classmethod
    def printed(
        cls,
        layout_mm: Sequence[tuple[float, float]],
        marker_size_mm: float = DEFAULT_MARKER_SIZE_MM,
        *,
        scale: float = 1.0,
    ) -> Scene:
        """The table laid out from a marker layout, as a technician would: each marker's
        centre at the layout's position, its black square `marker_size_mm` wide.

        `scale` prints the layout at another scale, about its centroid (a drawing or jig
        printed at 102 %, a layout measured with the wrong ruler); the markers keep their
        size. A robot calibration that maps such a table to the unscaled layout fits it
        perfectly, and only the markers' known size shows that the map is wrong.
        """
        points = np.asarray(layout_mm, dtype=np.float64).reshape(-1, 2)
        centre = points.mean(axis=0)
        placed = centre + float(scale) * (points - centre)
        return cls(
            marker_positions_mm=[(float(x), float(y)) for x, y in placed],
            marker_size_mm=float(marker_size_mm),
        )

    @property
    def marker_ids(self) -> list[int]:
        """Marker i is at marker_positions_mm[i]."""
        return list(range(len(self.marker_positions_mm)))

    def place_workpiece(
        self, shape: str | WorkpieceShape, x_mm: float, y_mm: float, rotation_deg: float = 0.0
    ) -> Workpiece:
        """Put a workpiece on the table; warn if it covers a marker's paper."""
        piece = Workpiece.named(shape, x_mm, y_mm, rotation_deg)
        outline = piece.outline_table_mm().astype(np.float32)
        for marker_id, corners in marker_corners_mm(self, paper=True).items():
            overlap, _ = cv2.intersectConvexConvex(
                cv2.convexHull(outline), corners.astype(np.float32)
            )
            if overlap > 0:
                logger.warning(
                    "workpiece %s at (%.1f, %.1f) covers marker %d's paper",
                    piece.shape.name,
                    x_mm,
                    y_mm,
                    marker_id,
                )
        self.workpieces.append(piece)
        return piece

    def clear_workpieces(self) -> None:
        """Take every workpiece off the table, and the bead on them with them."""
        self.workpieces.clear()
        self.bead = None

    def shift_workpieces(self, dx_mm: float, dy_mm: float) -> None:
        """Slide every workpiece on the table by dx, dy mm (a part knocked after matching)."""
        self.workpieces = [
            dataclasses.replace(p, x_mm=p.x_mm + float(dx_mm), y_mm=p.y_mm + float(dy_mm))
            for p in self.workpieces
        ]

    def present_next_part(self) -> None:
        """Take the parts off the table and lay fresh ones where they were (a production
        order's next part: same shapes and poses, nothing sprayed on them yet).

        Through `clear_workpieces` and `place_workpiece`, so whatever the scene keeps
        per part (the bead dispensed on it) goes with the old ones.
        """
        fresh = [(p.shape, p.x_mm, p.y_mm, p.rotation_deg) for p in self.workpieces]
        self.clear_workpieces()
        for shape, x_mm, y_mm, rotation_deg in fresh:
            self.place_workpiece(shape, x_mm, y_mm, rotation_deg)

    def snapshot(self) -> Scene:
        """A copy whose lists are its own, so a render in a worker thread is not disturbed by
        workpieces being moved on the event loop meanwhile."""
        return dataclasses.replace(
            self,
            workpieces=list(self.workpieces),
            marker_positions_mm=list(self.marker_positions_mm),
        )

    def _background_key(self) -> tuple[Hashable, ...]:
        return (
            tuple((float(x), float(y)) for x, y in self.marker_positions_mm),
            float(self.printed_marker_size_mm),
            float(self.quiet_zone_mm),
            tuple(self.table_bgr),
            float(self.table_texture),
            int(self.seed),
        )


# --- ground truth -----------------------------------------------------------------------------


def marker_corners_mm(scene: Scene, *, paper: bool = False) -> dict[int, NDArray[np.float64]]:
    """Table corners (4×2 mm) of each marker's black square, in ArUco order.

    ArUco order is the marker image's top-left, top-right, bottom-right, bottom-left. With
    `paper`, the corners of the white sheet (quiet zone included) instead. As printed: a
    print scale in the scene's degradations makes them larger about the same centre.
    """
    half = scene.printed_marker_size_mm / 2.0 + (scene.quiet_zone_mm if paper else 0.0)
    offsets = np.array([[-half, -half], [-half, half], [half, half], [half, -half]])
    return {
        i: np.asarray(c, dtype=np.float64) + offsets
        for i, c in enumerate(scene.marker_positions_mm)
    }


def marker_corner_pixels(
    scene: Scene, model: CameraModel = DEFAULT_CAMERA_MODEL
) -> dict[int, NDArray[np.float64]]:
    """Where each marker's four corners appear (4×2 px, ArUco order)."""
    return {i: model.table_to_pixel(c) for i, c in marker_corners_mm(scene).items()}


def marker_centre_pixels(
    scene: Scene, model: CameraModel = DEFAULT_CAMERA_MODEL
) -> dict[int, tuple[float, float]]:
    """Where each marker's centre appears: the projection of the centre point itself.

    (Not the mean of the projected corners, which perspective shifts slightly.)
    """
    centres = model.table_to_pixel(np.asarray(scene.marker_positions_mm, dtype=np.float64))
    return {i: (float(u), float(v)) for i, (u, v) in enumerate(centres)}


def workpiece_outline_pixels(
    workpiece: Workpiece, model: CameraModel = DEFAULT_CAMERA_MODEL
) -> NDArray[np.float64]:
    """The workpiece outline's vertices in the image (N×2 px)."""
    return model.table_to_pixel(workpiece.outline_table_mm())


# --- rasterising with exact area coverage ----------------------------------------------------


def polygon_coverage(
    polygons: Sequence[ArrayLike], shape: tuple[int, int], supersample: int = 8
) -> NDArray[np.float32]:
    """Fraction of each pixel covered by non-overlapping polygons (pixel coords, N×2 each).

    Exact along rows (span ends contribute their fractional overlap) and supersampled
    `supersample`× across rows, so an edge is placed to ~1/100 px whatever its slope — unlike
    `cv2.fillPoly`, which grows shapes by half a pixel. Pixel (r, c) is centred at (c, r).
    """
    rows, cols = shape
    scan_y = (np.arange(rows * supersample) + 0.5) / supersample - 0.5
    diff = np.zeros((rows * supersample, cols + 2), dtype=np.float64)
    for polygon in polygons:
        pts = np.asarray(polygon, dtype=np.float64)
        x1, y1 = pts[:, 0], pts[:, 1]
        x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
        first, last = np.searchsorted(scan_y, [y1.min(), y1.max()])
        if last <= first:
            continue
        y = scan_y[first:last, None]
        crosses = ((y1 <= y) & (y < y2)) | ((y2 <= y) & (y < y1))
        with np.errstate(divide="ignore", invalid="ignore"):
            x = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        x = np.sort(np.where(crosses, x, np.inf), axis=1)
        line = np.broadcast_to(np.arange(first, last)[:, None], x.shape)
        for column, sign in ((0, 1.0), (1, -1.0)):  # span starts add coverage, ends remove it
            ends = x[:, column::2]
            ok = np.isfinite(ends)
            where = np.clip(ends[ok], -0.5, cols - 0.5)
            pixel = np.floor(where + 0.5).astype(np.int64)
            inside = pixel + 0.5 - where  # part of the first pixel right of the span end
            line_ok = line[:, column::2][ok]
            np.add.at(diff, (line_ok, pixel), sign * inside)
            np.add.at(diff, (line_ok, pixel + 1), sign * (1.0 - inside))
    coverage = np.cumsum(diff, axis=1)[:, :cols]
    coverage = coverage.reshape(rows, supersample, cols).mean(axis=1)
    return np.clip(coverage, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class _TableGrid:
    """The internal table image: pixel (row r, col c) is centred at (x0 + c·res, y0 + r·res)."""

    x0: float
    y0: float
    res: float
    cols: int
    rows: int

    def to_px(self, table_xy: ArrayLike) -> NDArray[np.float64]:
        xy = np.asarray(table_xy, dtype=np.float64)
        return np.stack(
            [(xy[..., 0] - self.x0) / self.res, (xy[..., 1] - self.y0) / self.res], axis=-1
        )


class _TableOptics:
    """Per-model render state: the table grid, the remap tables, and the blur to apply."""

    def __init__(self, model: CameraModel) -> None:
        rays = normalised_pixel_grid(model)
        table_xy = model.rays_to_table(rays)
        margin = 5.0  # mm, so bilinear sampling never reaches the grid's edge
        res = TABLE_MM_PER_PX
        x0 = math.floor((float(table_xy[..., 0].min()) - margin) / res) * res
        y0 = math.floor((float(table_xy[..., 1].min()) - margin) / res) * res
        cols = math.ceil((float(table_xy[..., 0].max()) + margin - x0) / res) + 1
        rows = math.ceil((float(table_xy[..., 1].max()) + margin - y0) / res) + 1
        self.grid = _TableGrid(x0, y0, res, cols, rows)
        src = self.grid.to_px(table_xy).astype(np.float32)
        self.map_x, self.map_y = cv2.convertMaps(src[..., 0], src[..., 1], cv2.CV_16SC2)
        # Band-limit at the table image's resolution: the footprint of one camera pixel on the
        # table is distance / focal length; the blur stands for that area plus the lens.
        centre = np.append(table_xy[model.height // 2, model.width // 2], 0.0)
        distance = float(np.linalg.norm(model.position_mm - centre))
        footprint_mm = distance / math.sqrt(model.fx * model.fy)
        self.blur_sigma = footprint_blur_sigma_px() * footprint_mm / res


class _RenderCache:
    """Small thread-safe LRU caches; renders run in worker threads, several at a time."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self._lock = threading.Lock()

    def get_or_build(self, key: Hashable, build: Any) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = build()  # outside the lock: building can take a second
        with self._lock:
            self._items[key] = value
            while len(self._items) > self._size:
                self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


# One of each: the camera looks at one table at a time, and each is rebuilt only when what it
# depends on changes (the camera moved, the markers, the parts, the bead). A second entry was
# only ever hit by tests switching back and forth, and cost the image process its size again.
_optics_cache = _RenderCache(1)  # ~12 MB: the remap tables
_background_cache = _RenderCache(1)  # ~45 MB: table image with markers
_frame_cache = _RenderCache(1)  # ~6 MB: the remapped table before light and noise


def clear_render_caches() -> None:
    """Drop every cached map and image (frees ~80 MB after heavy use)."""
    for cache in (_optics_cache, _background_cache, _frame_cache):
        cache.clear()
    release_chessboard_state()


def release_chessboard_state() -> None:
    """Drop what only chessboard views need: their cached views (~2 MB each), the board's
    texture and every pixel's undistorted ray (~32 MB per camera model).

    Called once the camera looks at the table again: the table's optics keep what they
    built from the rays, and a later camera calibration computes them again (once per
    model, a second or so)."""
    clear_chessboard_cache()
    normalised_pixel_grid.cache_clear()


def _optics(model: CameraModel) -> _TableOptics:
    return _optics_cache.get_or_build(model, lambda: _TableOptics(model))


def _composite(
    image: NDArray[np.uint8],
    grid: _TableGrid,
    polygons_mm: Sequence[NDArray[np.float64]],
    colour: Sequence[float],
    blur_sigma: float,
) -> None:
    """Paint `colour` over `image` inside the polygons, with exact, band-limited edges.

    The coverage mask is blurred rather than the image, so each layer is blurred once; this
    is exact where the layer underneath is uniform (paper under ink) and close enough over the
    slowly varying table texture.
    """
    pad = math.ceil(4.0 * blur_sigma) + 2
    polygons_px = [grid.to_px(p) for p in polygons_mm]
    everything = np.vstack(polygons_px)
    c0 = max(math.floor(everything[:, 0].min()) - pad, 0)
    r0 = max(math.floor(everything[:, 1].min()) - pad, 0)
    c1 = min(math.ceil(everything[:, 0].max()) + pad + 1, grid.cols)
    r1 = min(math.ceil(everything[:, 1].max()) + pad + 1, grid.rows)
    if c1 <= c0 or r1 <= r0:
        return  # outside the camera's view
    local = [p - (c0, r0) for p in polygons_px]
    alpha = polygon_coverage(local, (r1 - r0, c1 - c0))
    if blur_sigma > 0:
        alpha = cast(NDArray[np.float32], cv2.GaussianBlur(alpha, (0, 0), blur_sigma))
    alpha = alpha[..., None]
    region = image[r0:r1, c0:c1].astype(np.float32)
    region = region * (1.0 - alpha) + np.asarray(colour, dtype=np.float32) * alpha
    image[r0:r1, c0:c1] = np.clip(np.rint(region), 0, 255).astype(np.uint8)


def _composite_bead(image: NDArray[np.uint8], optics: _TableOptics, bead: BeadLayer) -> None:
    """Paint the bead over the table image, band-limited like every other edge."""
    grid = optics.grid
    pad = math.ceil(4.0 * optics.blur_sigma) + 2
    found = bead_coverage(bead, grid.to_px, grid.res, (grid.rows, grid.cols), pad)
    if found is None:
        return
    r0, c0, alpha = found
    if optics.blur_sigma > 0:
        alpha = cast(NDArray[np.float32], cv2.GaussianBlur(alpha, (0, 0), optics.blur_sigma))
    r1, c1 = r0 + alpha.shape[0], c0 + alpha.shape[1]
    weight = alpha[..., None]
    region = image[r0:r1, c0:c1].astype(np.float32)
    region = region * (1.0 - weight) + np.asarray(BEAD_BGR, dtype=np.float32) * weight
    image[r0:r1, c0:c1] = np.clip(np.rint(region), 0, 255).astype(np.uint8)


def _marker_ink_polygons(scene: Scene, marker_id: int) -> list[NDArray[np.float64]]:
    """The black cells of one marker as table-frame squares (rows along +x, columns along +y)."""
    dictionary = aruco_dictionary()
    cells = dictionary.markerSize + 2
    bits = cv2.aruco.generateImageMarker(dictionary, marker_id, cells)
    size = scene.printed_marker_size_mm
    cell = size / cells
    cx, cy = scene.marker_positions_mm[marker_id]
    x_top, y_left = cx - size / 2.0, cy - size / 2.0
    squares = []
    for row, col in zip(*np.nonzero(bits == 0), strict=True):
        x, y = x_top + row * cell, y_left + col * cell
        squares.append(np.array([[x, y], [x + cell, y], [x + cell, y + cell], [x, y + cell]]))
    return squares


def _build_background(scene: Scene, optics: _TableOptics) -> NDArray[np.uint8]:
    """The table image with its texture and the printed markers (no workpieces)."""
    grid = optics.grid
    rng = np.random.default_rng(scene.seed)
    # The table image is ~15 M pixels: each step writes into one of two buffers (60 MB each)
    # rather than into a fresh temporary, whose pages would be faulted in again each time.
    texture = np.zeros((grid.rows, grid.cols), dtype=np.float32)
    layer = np.empty_like(texture)
    for scale_mm, weight in ((40.0, 1.0), (6.0, 0.4)):  # broad mottling and finer grain
        coarse = rng.standard_normal(
            (
                math.ceil(grid.rows * grid.res / scale_mm) + 2,
                math.ceil(grid.cols * grid.res / scale_mm) + 2,
            )
        )
        cv2.resize(
            coarse.astype(np.float32),
            (grid.cols, grid.rows),
            dst=layer,
            interpolation=cv2.INTER_CUBIC,
        )
        texture += np.multiply(layer, weight, out=layer)
    texture *= scene.table_texture / max(float(texture.std()), 1e-6)
    image = np.empty((grid.rows, grid.cols, 3), dtype=np.uint8)
    for channel, level in enumerate(scene.table_bgr):
        np.add(texture, level, out=layer)
        image[..., channel] = np.clip(np.rint(layer, out=layer), 0, 255, out=layer)
    papers = marker_corners_mm(scene, paper=True)
    for marker_id in scene.marker_ids:
        _composite(image, grid, [papers[marker_id]], PAPER_BGR, optics.blur_sigma)
        _composite(image, grid, _marker_ink_polygons(scene, marker_id), INK_BGR, optics.blur_sigma)
    return image


def _build_frame(scene: Scene, model: CameraModel) -> NDArray[Any]:
    """The camera's noiseless view of a snapshot of the scene, as the frame cache keeps it:
    the remapped table before its light (uint8 H×W×3, a quarter of the lit frame's size),
    or, with degradations, the lit frame with their lens and light applied (float32: their
    blur and remap cost more than a frame's noise, so they are not redone per frame)."""
    optics = _optics(model)
    background = _background_cache.get_or_build(
        (model, scene._background_key()), lambda: _build_background(scene, optics)
    )
    table = background
    if scene.workpieces or scene.bead:
        table = background.copy()  # the cached background stays as it is
        for piece in scene.workpieces:
            _composite(
                table, optics.grid, [piece.outline_table_mm()], piece.colour_bgr,
                optics.blur_sigma,
            )  # fmt: skip
    if scene.bead:
        _composite_bead(table, optics, scene.bead)
    frame = cv2.remap(
        table, optics.map_x, optics.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    if scene.degradations is None:
        return frame
    lit = frame.astype(np.float32) * lighting_gain(model, scene.vignetting, scene.light_gradient)
    return scene.degradations.apply_to_light(lit)


def render_table(
    scene: Scene,
    model: CameraModel = DEFAULT_CAMERA_MODEL,
    rng: np.random.Generator | None = None,
) -> NDArray[np.uint8]:
    """One camera frame of the table (uint8 BGR, model.height × model.width).

    Without `rng` the sensor noise is seeded from `scene.seed`, so the same scene gives the
    same frame; pass a generator to get a fresh noise pattern per frame. The scene's
    degradations, if any, are applied (their lens and light parts cached with the frame).
    """
    snapshot = scene.snapshot()
    clean: NDArray[Any] = _clean_frame(snapshot, model)
    if snapshot.defocus_px > 0:
        clean = cv2.GaussianBlur(clean, (0, 0), float(snapshot.defocus_px))
    if snapshot.exposure != 1.0:
        clean = clean * np.float32(snapshot.exposure)
    degradations = snapshot.degradations
    sigma = snapshot.noise_sigma
    if degradations is not None and degradations.noise_sigma is not None:
        sigma = degradations.noise_sigma
    frame = expose(clean, sigma, rng or np.random.default_rng(snapshot.seed))
    return degradations.apply_to_image(frame) if degradations is not None else frame


def draw_table_ahead(scene: Scene, model: CameraModel = DEFAULT_CAMERA_MODEL) -> None:
    """Build the noiseless frame of `scene` into the cache and deliver nothing: a
    `render_table` of the same scene then only adds the sensor's noise."""
    _clean_frame(scene.snapshot(), model)


def _clean_frame(snapshot: Scene, model: CameraModel) -> NDArray[np.float32]:
    """The lit, noiseless frame (float32 H×W×3) of a snapshot, drawn from the cache or into
    it, and lit here unless the cache holds it lit (`_build_frame`)."""
    bead = snapshot.bead.key if snapshot.bead else None
    light = (float(snapshot.vignetting), float(snapshot.light_gradient))
    pieces, degradations = tuple(snapshot.workpieces), snapshot.degradations
    key = (model, snapshot._background_key(), pieces, bead, light, degradations)
    drawn = _frame_cache.get_or_build(key, lambda: _build_frame(snapshot, model))
    if drawn.dtype != np.uint8:
        return cast(NDArray[np.float32], drawn)
    return np.multiply(drawn, lighting_gain(model, *light), dtype=np.float32)
