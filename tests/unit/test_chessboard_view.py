"""The chessboard view's map from camera rays to the board: one homography per pose."""

from __future__ import annotations

import numpy as np

from server.drivers.sim.camera_chessboard import (
    BOARD_MM_PER_PX,
    DEFAULT_CHESSBOARD,
    BoardPose,
    _board_texture,
    _ray_to_texture,
    default_chessboard_poses,
)


def _meeting_point_mm(pose: BoardPose, ray: np.ndarray) -> tuple[np.ndarray, float]:
    """Where the ray (x, y, 1) meets the board's plane, in board mm, and at what depth."""
    rot, tvec = pose.rotation, np.asarray(pose.tvec, dtype=np.float64)
    normal = rot[:, 2]
    depth = float(normal @ tvec) / float(normal @ ray)
    board = rot.T @ (depth * ray - tvec)
    return board, depth


def test_the_homography_takes_each_ray_to_where_it_meets_the_board() -> None:
    _, origin_x, origin_y = _board_texture(DEFAULT_CHESSBOARD)
    rng = np.random.default_rng(7)
    for pose in default_chessboard_poses():
        to_texture = _ray_to_texture(pose, origin_x, origin_y)
        for x, y in rng.uniform(-0.6, 0.6, size=(20, 2)):
            ray = np.array([x, y, 1.0])
            board, depth = _meeting_point_mm(pose, ray)
            u, v, w = to_texture @ ray
            assert abs(w - 1.0 / depth) < 1e-12
            assert abs(u / w - (board[0] - origin_x) / BOARD_MM_PER_PX) < 1e-6
            assert abs(v / w - (board[1] - origin_y) / BOARD_MM_PER_PX) < 1e-6
            assert abs(board[2]) < 1e-9  # on the board's plane


def test_a_ray_meeting_the_plane_behind_the_camera_has_a_negative_third_coordinate() -> None:
    _, origin_x, origin_y = _board_texture(DEFAULT_CHESSBOARD)
    # a board tilted 80° about its x axis, 500 mm ahead: rays far enough up meet its plane
    # behind the camera
    tilted = BoardPose((np.deg2rad(80.0), 0.0, 0.0), (0.0, 0.0, 500.0))
    to_texture = _ray_to_texture(tilted, origin_x, origin_y)
    depths = []
    for y in (-3.0, 3.0):
        ray = np.array([0.0, y, 1.0])
        _, depth = _meeting_point_mm(tilted, ray)
        assert np.sign((to_texture @ ray)[2]) == np.sign(depth)
        depths.append(depth)
    assert min(depths) < 0 < max(depths)  # one ray meets it ahead, the other behind
