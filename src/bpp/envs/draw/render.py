"""Rasterisation of the drawing scene at any resolution, directly (no resize of a 512 render).

Everything is drawn from geometry in canvas pixels with analytic, anti-aliased coverage: a pixel's coverage
by a thick line is ``clip((half_width - distance) / pixel_size + 0.5, 0, 1)`` where the distance is measured
from the pixel centre to the line's centre segment. Ink coverage is the *maximum* over segments, so the ink
layer does not depend on how a path is split into steps: replaying a stored episode reproduces every frame
bit for bit.
"""

from __future__ import annotations

import numpy as np

from bpp.envs.draw.geometry import BOARD_CENTER, CANVAS_SIZE, board_corners, unit_to_canvas

BACKGROUND_RGB = (255, 255, 255)
BOARD_EDGE_RGB = (0, 0, 0)
BOARD_TOP_EDGE_RGB = (255, 0, 0)
HELPER_LINE_RGB = (211, 211, 211)
INK_RGB = (0, 0, 255)
CURSOR_RGB = (48, 156, 54)
CURSOR_OUTLINE_RGB = (255, 255, 255)

BOARD_EDGE_WIDTH = 8.0
HELPER_LINE_WIDTH = 8.0
INK_WIDTH = 12.0
CURSOR_RADIUS = 15.0
CURSOR_OUTLINE_WIDTH = 2.0


def pixel_centers(resolution: int, rows: slice = slice(None), cols: slice = slice(None)):
    """Canvas coordinates of pixel centres of a `resolution`-sized image, restricted to rows x cols.

    Returns (x, y) arrays of shape (H, W).
    """
    scale = CANVAS_SIZE / resolution
    r = np.arange(resolution, dtype=np.float64)[rows]
    c = np.arange(resolution, dtype=np.float64)[cols]
    return np.meshgrid((c + 0.5) * scale, (r + 0.5) * scale)


def segment_distance(x: np.ndarray, y: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance from points (x, y) of shape S to the nearest of (M, 4) segments [x0, y0, x1, y1]; shape S."""
    best = np.full(x.shape, np.inf)
    for x0, y0, x1, y1 in np.asarray(segments, dtype=np.float64):
        dx, dy = x1 - x0, y1 - y0
        length2 = dx * dx + dy * dy
        px, py = x - x0, y - y0
        if length2 > 0.0:
            t = np.clip((px * dx + py * dy) / length2, 0.0, 1.0)
            px = px - t * dx
            py = py - t * dy
        np.minimum(best, np.sqrt(px * px + py * py), out=best)
    return best


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(N, 2) polyline -> (max(N-1, 1), 4) segments; a single point becomes a zero-length segment (a dot)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(points) == 1:
        return np.concatenate([points, points], axis=1)
    return np.concatenate([points[:-1], points[1:]], axis=1)


def coverage(distance: np.ndarray, half_width: float, pixel_size: float) -> np.ndarray:
    """Anti-aliased coverage in [0, 1] of a pixel at `distance` from a shape's centre line."""
    return np.clip((half_width - distance) / pixel_size + 0.5, 0.0, 1.0)


def _blend(image: np.ndarray, cover: np.ndarray, rgb) -> None:
    image *= 1.0 - cover[..., None]
    image += cover[..., None] * np.asarray(rgb, dtype=np.float64)


def _bbox(points: np.ndarray, margin: float, resolution: int) -> tuple[slice, slice] | None:
    """Pixel rows/cols whose centres may lie within `margin` canvas px of `points`; None if off-image."""
    scale = resolution / CANVAS_SIZE
    lo = np.floor((points.min(axis=0) - margin) * scale - 0.5).astype(int)
    hi = np.ceil((points.max(axis=0) + margin) * scale + 0.5).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, resolution)
    if np.any(hi <= lo):
        return None
    return slice(lo[1], hi[1]), slice(lo[0], hi[0])


def render_board(resolution: int, angle: float, center=BOARD_CENTER) -> np.ndarray:
    """The static scene (background, helper lines, board edges) as a float64 (H, W, 3) image in [0, 255]."""
    x, y = pixel_centers(resolution)
    pixel = CANVAS_SIZE / resolution
    image = np.empty((resolution, resolution, 3))
    image[:] = BACKGROUND_RGB
    helpers = unit_to_canvas(
        np.array([[0, 0, 1, 1], [0, 1, 1, 0], [0.5, 0, 0.5, 1], [0, 0.5, 1, 0.5]], dtype=np.float64).reshape(-1, 2),
        angle,
        center,
    ).reshape(-1, 4)
    _blend(image, coverage(segment_distance(x, y, helpers), HELPER_LINE_WIDTH / 2, pixel), HELPER_LINE_RGB)
    tl, tr, br, bl = board_corners(angle, center)
    edges = np.array([np.r_[tr, br], np.r_[br, bl], np.r_[bl, tl]])
    _blend(image, coverage(segment_distance(x, y, edges), BOARD_EDGE_WIDTH / 2, pixel), BOARD_EDGE_RGB)
    top = np.r_[tl, tr][None]
    _blend(image, coverage(segment_distance(x, y, top), BOARD_EDGE_WIDTH / 2, pixel), BOARD_TOP_EDGE_RGB)
    return image


class SceneRenderer:
    """Renders observations of one episode at a fixed resolution, adding ink incrementally.

    Usage: ``r = SceneRenderer(96, angle)``; after every physics step ``r.add_ink(path)`` with the cursor
    path drawn while the pen was down; ``r.frame(cursor_xy)`` gives the (H, W, 3) uint8 image.
    """

    def __init__(self, resolution: int, angle: float, center=BOARD_CENTER):
        if resolution < 8:
            raise ValueError(f"image resolution must be at least 8 px, got {resolution}")
        self.resolution = resolution
        self.pixel = CANVAS_SIZE / resolution
        self.board = render_board(resolution, angle, center)
        self.ink = np.zeros((resolution, resolution))  # ink coverage in [0, 1]
        self.canvas = self._composite(slice(None), slice(None))  # board + ink, uint8

    def _composite(self, rows: slice, cols: slice) -> np.ndarray:
        image = self.board[rows, cols].copy()
        _blend(image, self.ink[rows, cols], INK_RGB)
        return np.rint(image).astype(np.uint8)

    def add_ink(self, path: np.ndarray) -> None:
        """Ink a (N, 2) canvas polyline (N >= 1) with the pen's width."""
        path = np.asarray(path, dtype=np.float64).reshape(-1, 2)
        box = _bbox(path, INK_WIDTH / 2 + self.pixel, self.resolution)
        if box is None:
            return
        rows, cols = box
        x, y = pixel_centers(self.resolution, rows, cols)
        cover = coverage(segment_distance(x, y, polyline_segments(path)), INK_WIDTH / 2, self.pixel)
        np.maximum(self.ink[rows, cols], cover, out=self.ink[rows, cols])
        self.canvas[rows, cols] = self._composite(rows, cols)

    def frame(self, cursor: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 observation with the cursor drawn on top (the pen state is proprioception only)."""
        image = self.canvas.copy()
        cursor = np.asarray(cursor, dtype=np.float64)
        outer = CURSOR_RADIUS + CURSOR_OUTLINE_WIDTH
        box = _bbox(cursor[None], outer + self.pixel, self.resolution)
        if box is not None:
            rows, cols = box
            x, y = pixel_centers(self.resolution, rows, cols)
            dist = np.hypot(x - cursor[0], y - cursor[1])
            patch = image[rows, cols].astype(np.float64)
            _blend(patch, coverage(dist, outer, self.pixel), CURSOR_OUTLINE_RGB)
            _blend(patch, coverage(dist, CURSOR_RADIUS, self.pixel), CURSOR_RGB)
            image[rows, cols] = np.rint(patch).astype(np.uint8)
        return image
