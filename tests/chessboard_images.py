"""Rendered photos of a chessboard: its texture, and that texture seen by a pinhole camera at a known pose."""

from __future__ import annotations

import cv2
import numpy as np

from services.calibration.intrinsics import Chessboard

TEXELS = 40
"""Texture texels per board square."""


def chessboard_texture(board: Chessboard) -> tuple[np.ndarray, np.ndarray]:
    """The board image (one white square of margin) and the (3, 3) map from board metres to its texels."""
    squares_x, squares_y = board.columns + 1, board.rows + 1
    image = np.full(((squares_y + 2) * TEXELS, (squares_x + 2) * TEXELS), 255, np.uint8)
    for row in range(squares_y):
        for column in range(squares_x):
            if (row + column) % 2 == 0:
                image[(row + 1) * TEXELS:(row + 2) * TEXELS, (column + 1) * TEXELS:(column + 2) * TEXELS] = 0
    scale, offset = TEXELS / board.square_m, 2 * TEXELS - 0.5  # board origin: the first inner corner
    return image, np.array([[scale, 0.0, offset], [0.0, scale, offset], [0.0, 0.0, 1.0]])


def board_centre(board) -> np.ndarray:
    """(3,) the centre of a Chessboard's inner corners or of a Charuco's squares, board frame, metres."""
    if isinstance(board, Chessboard):
        return np.array([(board.columns - 1) / 2, (board.rows - 1) / 2, 0.0]) * board.square_m
    return np.array([board.columns / 2, board.rows / 2, 0.0]) * board.square_m


def render_board(texture: np.ndarray, texel_from_board: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                 size: tuple[int, int], distortion_map: tuple[np.ndarray, np.ndarray] | None = None,
                 seed: int = 0) -> np.ndarray:
    """(H, W) uint8: the board seen by camera ``K`` with ``T_camera_board = [R | t]`` in an image ``size`` = (W, H),
    grey background, noise of 2 grey levels; ``distortion_map``: remap() maps applying a lens distortion."""
    pixel_from_board = K @ np.column_stack([R[:, 0], R[:, 1], t])
    image = cv2.warpPerspective(texture, pixel_from_board @ np.linalg.inv(texel_from_board), size,
                                flags=cv2.INTER_AREA, borderValue=128)
    if distortion_map is not None:
        image = cv2.remap(image, *distortion_map, cv2.INTER_LINEAR, borderValue=128)
    noise = np.random.default_rng(seed).normal(0.0, 2.0, image.shape)
    return np.clip(image + noise, 0, 255).astype(np.uint8)
