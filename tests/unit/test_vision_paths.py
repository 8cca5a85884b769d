"""Spray paths: offsets, fill lines and the execution order of the polylines."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.vision.outlines import polygon_area_centroid
from server.vision.paths import (
    SprayPattern,
    fill_lines,
    fill_size,
    offset_polygon,
    spray_polylines,
)

SQUARE = np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 50.0], [0.0, 50.0]])
# the simulator's L bracket: legs 100 and 70 mm, 30 mm wide (concave at (30, 30))
L_SHAPE = np.array([[0, 0], [100, 0], [100, 30], [30, 30], [30, 70], [0, 70]], dtype=float)
# a U: two 20 mm prongs with a 20 mm slot between them
U_SHAPE = np.array(
    [[0, 0], [60, 0], [60, 60], [40, 60], [40, 20], [20, 20], [20, 60], [0, 60]], dtype=float
)


def area(polygon: np.ndarray) -> float:
    return polygon_area_centroid(polygon)[0]


def distance_to_boundary(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    a, b = polygon, np.roll(polygon, -1, axis=0)
    ab = b - a
    rel = points[:, None, :] - a[None]
    t = np.clip((rel * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * ab, axis=-1).min(axis=1)


def inside(polygon: np.ndarray, point: np.ndarray) -> bool:
    import cv2

    return cv2.pointPolygonTest(polygon.astype(np.float32), tuple(map(float, point)), True) > -1e-3


def turned(polygon: np.ndarray, degrees: float, shift: tuple[float, float]) -> np.ndarray:
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return polygon @ rot.T + shift


# --- offset ----------------------------------------------------------------------------------


@pytest.mark.parametrize("d", [5.0, 1.0, -1.0, -5.0, -20.0])
def test_square_offset_has_the_expected_area(d: float) -> None:
    grown = offset_polygon(SQUARE, d)
    assert len(grown) == 4
    assert area(grown) == pytest.approx((50.0 + 2 * d) ** 2)


@settings(max_examples=60, deadline=None)
@given(
    width=st.floats(20, 300),
    height=st.floats(20, 300),
    fraction=st.floats(-0.45, 0.45),
    degrees=st.floats(-180, 180),
)
def test_rectangle_offset_area_anywhere(
    width: float, height: float, fraction: float, degrees: float
) -> None:
    d = fraction * min(width, height)
    rect = turned(np.array([[0, 0], [width, 0], [width, height], [0, height]]), degrees, (400, 0))
    result = offset_polygon(rect, d)
    assert area(result) == pytest.approx((width + 2 * d) * (height + 2 * d), rel=1e-6)
    assert area(result) > 0  # counter-clockwise


def test_clockwise_input_gives_the_same_counter_clockwise_offset() -> None:
    assert area(offset_polygon(SQUARE[::-1], -5.0)) == pytest.approx(1600.0)


@pytest.mark.parametrize("d", [3.0, -3.0, -10.0, -14.0])
def test_concave_l_shape_offset(d: float) -> None:
    result = offset_polygon(L_SHAPE, d)
    assert len(result) == 6
    assert area(result) == pytest.approx((30 + 2 * d) * (140 + 2 * d))
    e = -d  # every corner moves diagonally by |d| in each axis
    expected = [(e, e), (100 - e, e), (100 - e, 30 - e), (30 - e, 30 - e), (30 - e, 70 - e),
                (e, 70 - e)]  # fmt: skip
    np.testing.assert_allclose(sorted(map(tuple, result)), sorted(expected), atol=1e-9)


def test_inward_offset_that_collapses_the_shape_is_refused() -> None:
    with pytest.raises(ValueError, match=r"inward offset of 25\.5 mm"):
        offset_polygon(SQUARE, -25.5)
    with pytest.raises(ValueError, match="vanish or split"):
        offset_polygon(L_SHAPE, -16.0)  # the 30 mm legs close up


def test_inward_offset_that_would_split_the_part_is_refused() -> None:
    dumbbell = np.array(
        [[0, 0], [40, 0], [40, 15], [60, 15], [60, 0], [100, 0], [100, 40], [60, 40], [60, 25],
         [40, 25], [40, 40], [0, 40]], dtype=float,
    )  # fmt: skip
    assert area(offset_polygon(dumbbell, -4.0)) > 0  # the 10 mm bridge is still there
    with pytest.raises(ValueError):
        offset_polygon(dumbbell, -6.0)  # the bridge is gone: two islands


def test_a_short_chamfer_is_absorbed_by_an_inward_offset() -> None:
    chamfered = np.array([[0, 0], [50, 0], [50, 49.5], [49.5, 50], [0, 50]], dtype=float)
    result = offset_polygon(chamfered, -3.0)
    np.testing.assert_allclose(sorted(map(tuple, result)), [(3, 3), (3, 47), (47, 3), (47, 47)])


def test_a_sharp_spike_is_bevelled_not_stretched() -> None:
    needle = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 10.0]])
    result = offset_polygon(needle, 2.0)
    assert np.max(distance_to_boundary(needle, result)) < 2.0 * 4.0 + 1e-9  # mitre limit
    assert result[:, 0].max() < 105.0


def test_outward_offset_that_closes_a_slot_is_refused() -> None:
    assert area(offset_polygon(U_SHAPE, 5.0)) > area(U_SHAPE)
    with pytest.raises(ValueError, match="outward offset"):
        offset_polygon(U_SHAPE, 12.0)


@pytest.mark.parametrize("d", [-5.0, 5.0])
def test_a_triangle_can_be_offset(d: float) -> None:
    """Every triangular part with a bead offset failed its run with PATH_INVALID: "zero-size
    array to reduction operation" (the crossing check found no pair of edges to test)."""
    triangle = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]])
    grown = offset_polygon(triangle, d)
    assert len(grown) >= 3 and (area(grown) > area(triangle)) == (d > 0)


def test_an_outline_that_crosses_itself_is_refused() -> None:
    bow_tie = SQUARE[[0, 2, 1, 3]]
    with pytest.raises(ValueError, match="crosses itself"):
        spray_polylines(bow_tie, SprayPattern())
    assert len(spray_polylines(SQUARE, SprayPattern())) == 1


# --- fill ------------------------------------------------------------------------------------


def check_segments(polygon: np.ndarray, segments: list[np.ndarray], angle_deg: float) -> None:
    """Every segment runs along the angle, ends on the boundary and stays inside."""
    direction = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    for seg in segments:
        assert seg.shape == (2, 2)
        along = seg[1] - seg[0]
        assert abs(along[0] * direction[1] - along[1] * direction[0]) < 1e-6
        assert np.all(distance_to_boundary(polygon, seg) < 1e-6)
        for t in np.linspace(0.05, 0.95, 10):
            assert inside(polygon, seg[0] + t * along)


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, -45.0, 179.0])
def test_fill_lines_are_spaced_and_inside(angle: float) -> None:
    polygon = turned(np.array([[0, 0], [120, 0], [120, 80], [0, 80]], float), 17.0, (400, -50))
    segments = fill_lines(polygon, 10.0, angle, zigzag=False)
    check_segments(polygon, segments, angle)
    normal = np.array([-math.sin(math.radians(angle)), math.cos(math.radians(angle))])
    offsets = sorted({round(float(seg[0] @ normal), 6) for seg in segments})
    np.testing.assert_allclose(np.diff(offsets), 10.0, atol=1e-6)
    # boustrophedon: consecutive lines run in opposite directions
    for first, second in itertools.pairwise(segments):
        assert (first[1] - first[0]) @ (second[1] - second[0]) < 0


def test_fill_lines_are_centred_on_the_part() -> None:
    segments = fill_lines(SQUARE, 10.0, 0.0, zigzag=False)
    assert sorted(seg[0, 1] for seg in segments) == pytest.approx([5, 15, 25, 35, 45])


def test_zigzag_joins_a_convex_fill_into_one_polyline() -> None:
    polylines = fill_lines(SQUARE, 10.0, 0.0, zigzag=True)
    assert len(polylines) == 1 and polylines[0].shape == (10, 2)


def test_concave_fill_stays_inside_and_goes_cell_by_cell() -> None:
    segments = fill_lines(U_SHAPE, 5.0, 0.0, zigzag=False)
    check_segments(U_SHAPE, segments, 0.0)
    assert sum(np.linalg.norm(s[1] - s[0]) for s in segments) == pytest.approx(
        (60 * 20 + 20 * 40 * 2) / 5.0
    )  # total length × spacing = area
    # each prong is filled in one go: the path crosses the slot at most twice
    crossings = sum(
        1
        for a, b in itertools.pairwise(segments)
        if (a[1][0] - 30.0) * (b[0][0] - 30.0) < 0 and min(a[1][1], b[0][1]) > 20.0
    )
    assert crossings <= 2
    for polyline in fill_lines(U_SHAPE, 5.0, 0.0, zigzag=True):
        for p, q in itertools.pairwise(polyline):
            for t in (0.25, 0.5, 0.75):
                assert inside(U_SHAPE, p + t * (q - p))


def test_fill_starts_near_the_given_point() -> None:
    segments = fill_lines(SQUARE, 10.0, 0.0, zigzag=False, start=(50.0, 50.0))
    assert np.allclose(segments[0][0], [50.0, 45.0])


def test_fill_rejects_a_bad_spacing() -> None:
    with pytest.raises(ValueError, match="spacing"):
        fill_lines(SQUARE, 0.0)


# --- whole pattern ---------------------------------------------------------------------------


def test_spray_polylines_outline_first_then_fill() -> None:
    pattern = SprayPattern(outline_offset_mm=-2.0, outline=True, fill="zigzag", fill_spacing_mm=8)
    paths = spray_polylines(L_SHAPE, pattern)
    bead = paths[0]
    np.testing.assert_array_equal(bead[0], bead[-1])  # closed
    assert area(bead[:-1]) == pytest.approx(26 * 136)
    assert len(paths) >= 2
    for polyline in paths[1:]:  # the fill lies inside the bead
        for point in polyline:
            assert inside(bead[:-1], point)


def test_spray_polylines_variants() -> None:
    assert len(spray_polylines(SQUARE, SprayPattern())) == 1  # outline only
    raster = spray_polylines(SQUARE, SprayPattern(outline=False, fill="raster", fill_spacing_mm=10))
    assert len(raster) == 5 and all(p.shape == (2, 2) for p in raster)
    grown = spray_polylines(SQUARE, SprayPattern(outline_offset_mm=3.0, fill="raster"))
    assert area(grown[0][:-1]) == pytest.approx(56.0**2)
    assert all(inside(SQUARE, p) for seg in grown[1:] for p in seg)  # fill stays on the part
    assert spray_polylines(SQUARE, SprayPattern(outline=False)) == []


def test_spray_pattern_validates() -> None:
    with pytest.raises(ValueError, match="fill must be one of"):
        SprayPattern(fill="spiral")
    with pytest.raises(ValueError, match="fill_spacing_mm"):
        SprayPattern(fill="zigzag", fill_spacing_mm=0.0)


# --- stopping and sizing the planning --------------------------------------------------------


class _Stop(Exception):
    pass


def test_a_checkpoint_that_raises_stops_the_planning_at_once() -> None:
    # Why: a thread cannot be cancelled, so cancellation and the time limit reach the
    # planner only through its checkpoint; what it raises must come out unchanged.
    calls = 0

    def checkpoint() -> None:
        nonlocal calls
        calls += 1
        if calls == 5:
            raise _Stop

    pattern = SprayPattern(outline_offset_mm=-2.0, fill="zigzag", fill_spacing_mm=1.0)
    with pytest.raises(_Stop):
        spray_polylines(U_SHAPE, pattern, checkpoint=checkpoint)
    assert calls == 5


@pytest.mark.parametrize("fill", ["zigzag", "raster"])
def test_the_planner_calls_its_checkpoint_in_every_loop(fill: str) -> None:
    # At least once per offset step, scan line, cell and join: no loop runs unchecked.
    calls = 0

    def checkpoint() -> None:
        nonlocal calls
        calls += 1

    pattern = SprayPattern(outline_offset_mm=-2.0, fill=fill, fill_spacing_mm=2.0)
    paths = spray_polylines(U_SHAPE, pattern, checkpoint=checkpoint)
    plain = spray_polylines(U_SHAPE, pattern)
    assert all(np.array_equal(a, b) for a, b in zip(paths, plain, strict=True))
    lines = math.floor((60 - 4) / 2.0 + 1e-9)
    assert calls >= 2 * lines  # the scan lines and the cells' rows, at the least


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0])
@pytest.mark.parametrize("shape", ["square", "l", "u"])
def test_fill_size_counts_the_strokes_the_raster_fill_has(shape: str, angle: float) -> None:
    polygon = {"square": SQUARE, "l": L_SHAPE, "u": U_SHAPE}[shape]
    lines, strokes = fill_size(polygon, 3.0, angle, max_lines=1000)
    assert strokes == len(fill_lines(polygon, 3.0, angle, zigzag=False))
    extent = {0.0: 1, 90.0: 0}.get(angle)
    if extent is not None:
        assert lines == math.floor(float(np.ptp(polygon[:, extent])) / 3.0 + 1e-9)


def test_fill_size_does_not_count_a_fill_of_too_many_lines() -> None:
    # 50 mm at 0.01 mm is 5000 lines: counting them would cost what the limit prevents.
    assert fill_size(SQUARE, 0.01, max_lines=1000) == (5000, None)
