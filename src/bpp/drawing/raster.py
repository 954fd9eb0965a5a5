"""The canvas's pixels and the lines drawn on them, at any resolution: where each pixel's centre lies on the 512-px
canvas, the distance from pixel centres to line segments, and a thick line's anti-aliased coverage of a pixel,
``clip((half_width - distance) / pixel_size + 0.5, 0, 1)``. DrawAnything-Sim's renderer draws its scene with them, and
the Chamfer metric inks its masks on the same pixel centres."""

from __future__ import annotations

import numpy as np

from bpp.drawing.geometry import CANVAS_SIZE

INK_WIDTH = 12.0
"""Width of a line of ink (canvas px): the pen's, in pictures and in the metric."""


def centers(resolution: int) -> np.ndarray:
    """(R,) canvas coordinate of each pixel row's (or column's) centre in a `resolution`-sized image."""
    return (np.arange(resolution, dtype=np.float64) + 0.5) * (CANVAS_SIZE / resolution)


def pixel_centers(resolution: int, rows: slice = slice(None), cols: slice = slice(None)):
    """Canvas coordinates of pixel centres of a `resolution`-sized image, restricted to rows x cols.

    Returns (x, y) arrays of shape (H, W).
    """
    coordinate = centers(resolution)
    return np.meshgrid(coordinate[cols], coordinate[rows])


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
