"""Coordinate frames of DrawAnything's canvas and board: DrawAnything-Sim's screen, and the canvas DrawAnything-Real's
ink is scored on.

Three frames are used throughout:

* **canvas** — pixels of the 512x512 canvas, x to the right, y *down*, origin at the top-left corner;
  the pixel in row i, column j covers [j, j+1) x [i, i+1) and its centre is (j + 0.5, i + 0.5).
* **unit** — a drawing's own frame: the unit square of the board, u to the right, v *up*, (0, 0) at the
  board's bottom-left corner. Drawing files and generated drawings live here.
* **board** — the board frame in canvas pixels: the unit square scaled to the board side, centred on the
  board centre, before the board rotation; i.e. "upright" canvas coordinates.

The board's top edge (v = 1) is drawn red so a policy can tell the board's orientation.
"""

from __future__ import annotations

import numpy as np

CANVAS_SIZE = 512
"""Side of the square canvas in pixels; all geometric constants below are in these pixels."""
BOARD_SIZE = 350.0
"""Side of the square drawing board."""
BOARD_CENTER = (256.0, 256.0)
MAX_BOARD_ANGLE = np.pi / 4
"""Board angles are drawn uniformly from [-MAX_BOARD_ANGLE, MAX_BOARD_ANGLE] (radians, counter-clockwise)."""


def rotation(angle: float) -> np.ndarray:
    """Counter-clockwise rotation *as seen on screen*, as a (2, 2) matrix acting on y-down canvas vectors."""
    c, s = np.cos(angle), np.sin(angle)
    # A visual counter-clockwise turn in a y-down frame is a clockwise matrix in maths convention.
    return np.array([[c, s], [-s, c]])


def unit_to_canvas(points: np.ndarray, angle: float, center=BOARD_CENTER) -> np.ndarray:
    """Map (..., 2) unit-square points (y up) onto the canvas for a board rotated by `angle`."""
    points = np.asarray(points, dtype=np.float64)
    local = np.stack([(points[..., 0] - 0.5) * BOARD_SIZE, (0.5 - points[..., 1]) * BOARD_SIZE], axis=-1)
    return local @ rotation(angle).T + np.asarray(center)


def canvas_to_unit(points: np.ndarray, angle: float, center=BOARD_CENTER) -> np.ndarray:
    """Inverse of :func:`unit_to_canvas`."""
    local = (np.asarray(points, dtype=np.float64) - np.asarray(center)) @ rotation(angle)
    return np.stack([local[..., 0] / BOARD_SIZE + 0.5, 0.5 - local[..., 1] / BOARD_SIZE], axis=-1)


def canvas_to_upright(points: np.ndarray, angle: float, center=BOARD_CENTER) -> np.ndarray:
    """Un-rotate (..., 2) canvas points about the board centre so the board is upright (angle 0)."""
    center = np.asarray(center)
    return (np.asarray(points, dtype=np.float64) - center) @ rotation(angle) + center


def board_corners(angle: float, center=BOARD_CENTER) -> np.ndarray:
    """(4, 2) canvas positions of the board corners: top-left, top-right, bottom-right, bottom-left."""
    return unit_to_canvas(np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]), angle, center)
