"""The simulated camera's renderer holds what the table it looks at needs, and no more.

It runs in the image process for the whole life of the server, so whatever its
caches keep is kept for good: one table's background, one frame before noise,
the camera's remap tables. Measured with tracemalloc, which sees numpy's and
OpenCV's arrays: two part layouts, two chessboard views, then the table again.
"""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np

from server.drivers.camera import _table_view
from server.drivers.sim.camera_scene import (
    DEFAULT_CAMERA_MODEL,
    Degradations,
    Scene,
    _frame_cache,
    clear_render_caches,
    default_chessboard_poses,
    render_chessboard_view,
    render_table,
)

# One background (~45 MB), one frame before light and noise (~6 MB), the remap tables
# (~12 MB), the light's gain (~8 MB), and room to spare; the renderer held about 240 MB
# here when every cache kept several tables and the chessboard's state stayed after
# calibration, and about 90 MB when it kept the frame lit, in float.
HELD_AT_MOST_MB = 80


def test_the_renderer_keeps_one_table_and_lets_the_chessboard_go() -> None:
    clear_render_caches()
    gc.collect()
    tracemalloc.start()
    try:
        scene = Scene()
        scene.place_workpiece("rect-120x80", 400.0, -75.0)
        render_table(scene)
        scene.shift_workpieces(20.0, 0.0)  # another part layout: another table
        render_table(scene)
        for pose in default_chessboard_poses()[:2]:  # a camera calibration's views
            render_chessboard_view(pose=pose)
        frame = _table_view(scene, DEFAULT_CAMERA_MODEL, np.random.default_rng(0))
        del frame
        gc.collect()
        held_mb = tracemalloc.get_traced_memory()[0] / 2**20
    finally:
        tracemalloc.stop()
        clear_render_caches()
    assert held_mb < HELD_AT_MOST_MB, f"the renderer holds {held_mb:.0f} MB"


def cached_frames() -> list[np.ndarray]:
    return list(_frame_cache._items.values())


def test_the_frame_before_noise_is_kept_as_the_eight_bit_remap_and_lit_per_frame() -> None:
    clear_render_caches()
    try:
        scene = Scene()
        scene.place_workpiece("rect-120x80", 400.0, -75.0)
        first = render_table(scene, rng=np.random.default_rng(1))
        (held,) = cached_frames()
        model = DEFAULT_CAMERA_MODEL
        assert held.dtype == np.uint8 and held.shape == (model.height, model.width, 3)
        again = render_table(scene, rng=np.random.default_rng(1))  # from the cache
        assert np.array_equal(first, again)
        assert (first.astype(np.int16) - held).std() > 1  # lit and noisy, not the cache itself
    finally:
        clear_render_caches()


def test_with_degradations_the_frame_is_kept_lit_as_their_lens_and_light_cost_more() -> None:
    clear_render_caches()
    try:
        scene = Scene(degradations=Degradations.realistic())
        render_table(scene, rng=np.random.default_rng(1))
        (held,) = cached_frames()
        assert held.dtype == np.float32
    finally:
        clear_render_caches()
