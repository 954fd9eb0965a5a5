"""Rasterisation of the drawing scene at any resolution, directly (no resize of a 512 render).

Everything is drawn from geometry in canvas pixels with analytic, anti-aliased coverage (:mod:`bpp.drawing.raster`):
a pixel's coverage
by a thick line is ``clip((half_width - distance) / pixel_size + 0.5, 0, 1)`` where the distance is measured
from the pixel centre to the line's centre segment. Ink coverage is the *maximum* over segments, so the ink
layer does not depend on how a path is split into steps: replaying a stored episode reproduces every frame
bit for bit.
"""

from __future__ import annotations

import numpy as np

from bpp.benchmarks.draw import physics
from bpp.drawing.geometry import BOARD_CENTER, CANVAS_SIZE, board_corners, unit_to_canvas
from bpp.drawing.raster import INK_WIDTH, centers, coverage, pixel_centers, polyline_segments, segment_distance

BACKGROUND_RGB = (255, 255, 255)
BOARD_EDGE_RGB = (0, 0, 0)
BOARD_TOP_EDGE_RGB = (255, 0, 0)
HELPER_LINE_RGB = (211, 211, 211)
INK_RGB = (0, 0, 255)
CURSOR_RGB = (48, 156, 54)
CURSOR_OUTLINE_RGB = (255, 255, 255)

BOARD_EDGE_WIDTH = 8.0
HELPER_LINE_WIDTH = 8.0
CURSOR_RADIUS = 15.0
CURSOR_OUTLINE_WIDTH = 2.0


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


BOARD_TILE = 8
"""Side in pixels of the tiles in which :func:`render_board` looks for the pixels its lines cover."""
WHOLE_BOARD_PIXELS = 96
"""Up to this resolution :func:`line_coverage` measures every pixel."""


def line_coverage(resolution: int, segments: np.ndarray, half_width: float) -> tuple[np.ndarray | slice, np.ndarray]:
    """The pixels that thick (M, 4) segments may cover, as (flat pixel indices or all of them, their coverage): exactly
    ``coverage(segment_distance(...), half_width, pixel)`` of a whole image at those pixels, and 0 at every other.

    Above WHOLE_BOARD_PIXELS, only pixels of the BOARD_TILE-sided tiles whose centre lies within the lines'
    reach plus half a tile's diagonal are measured: a pixel's distance differs from its tile centre's by at most
    that half diagonal. (At 224 px, 3x faster than measuring every pixel; below, the tiles cost more than they save.)
    """
    pixel = CANVAS_SIZE / resolution
    if resolution <= WHOLE_BOARD_PIXELS:
        x, y = pixel_centers(resolution)
        return slice(None), coverage(segment_distance(x, y, segments), half_width, pixel).reshape(-1)
    coordinate = centers(resolution)
    reach = half_width + pixel  # coverage is exactly 0 from half_width + pixel / 2 on
    tiles = -(-resolution // BOARD_TILE)
    tile = BOARD_TILE * pixel
    tile_x, tile_y = np.meshgrid(*[(np.arange(tiles) + 0.5) * tile] * 2)
    rows, cols = np.nonzero(segment_distance(tile_x, tile_y, segments) < reach + tile * np.sqrt(0.5))
    offsets = np.arange(BOARD_TILE)
    r = (rows[:, None] * BOARD_TILE + offsets)[:, :, None]  # (n, TILE, 1)
    c = (cols[:, None] * BOARD_TILE + offsets)[:, None, :]  # (n, 1, TILE)
    flat = (r * resolution + c)[(r < resolution) & (c < resolution)]
    distance = segment_distance(coordinate[flat % resolution], coordinate[flat // resolution], segments)
    return flat, coverage(distance, half_width, pixel)


def upright_points(points: np.ndarray, angle: float) -> np.ndarray:
    """(..., 2) canvas points turned about the board's centre so that a board at `angle` stands upright
    (:func:`~bpp.drawing.geometry.canvas_to_upright`'s map), written out per coordinate: a point maps to
    the same bits whatever array it comes in, so the env's board view and :func:`render_frames`' agree bit for bit
    (a matrix product may round differently for arrays of different lengths)."""
    p = np.asarray(points, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    dx, dy = p[..., 0] - BOARD_CENTER[0], p[..., 1] - BOARD_CENTER[1]
    return np.stack([dx * c - dy * s + BOARD_CENTER[0], dx * s + dy * c + BOARD_CENTER[1]], axis=-1)


def render_board(resolution: int, angle: float, center=BOARD_CENTER) -> np.ndarray:
    """The static scene (background, helper lines, board edges) as a float64 (H, W, 3) image in [0, 255]."""
    image = np.empty((resolution * resolution, 3))
    image[:] = BACKGROUND_RGB
    helpers = unit_to_canvas(
        np.array([[0, 0, 1, 1], [0, 1, 1, 0], [0.5, 0, 0.5, 1], [0, 0.5, 1, 0.5]], dtype=np.float64).reshape(-1, 2),
        angle,
        center,
    ).reshape(-1, 4)
    tl, tr, br, bl = board_corners(angle, center)
    edges = np.array([np.r_[tr, br], np.r_[br, bl], np.r_[bl, tl]])
    top = np.r_[tl, tr][None]
    # Blending a zero coverage leaves a pixel's value exactly as it is, so only the covered pixels are blended.
    for segments, half_width, rgb in (
        (helpers, HELPER_LINE_WIDTH / 2, HELPER_LINE_RGB),
        (edges, BOARD_EDGE_WIDTH / 2, BOARD_EDGE_RGB),
        (top, BOARD_EDGE_WIDTH / 2, BOARD_TOP_EDGE_RGB),
    ):
        pixels, cover = line_coverage(resolution, segments, half_width)
        patch = image[pixels]
        _blend(patch, cover, rgb)
        image[pixels] = patch
    return image.reshape(resolution, resolution, 3)


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


# --------------------------------------------------------------------------- frames of a recorded episode
def ink_segments(states: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An episode's ink as (M, 4) float64 segments [x0, y0, x1, y1] and the (M,) step that inks each.

    Step i inks the path of ``physics.control_step(states[i], actions[i])`` if its pen flag is down; computed once,
    it can be cached and passed to :func:`render_frames`.
    """
    states = np.asarray(states, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    down = np.flatnonzero(actions[:, 2] > physics.PEN_THRESHOLD)
    if not len(down):
        return np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    paths = physics.control_steps(states[down], actions[down])[1]  # (D, SUBSTEPS + 1, 2): polylines of 11 points
    segments = np.concatenate([paths[:, :-1], paths[:, 1:]], axis=2).reshape(-1, 4)  # as polyline_segments
    return segments, np.repeat(down, physics.SUBSTEPS).astype(np.int64)


def _windows(lo: np.ndarray, width: int, resolution: int) -> np.ndarray:
    """(N, width) pixel indices lo + [0, width), clipped into the image (a clipped pixel repeats)."""
    return np.clip(lo[:, None] + np.arange(width), 0, resolution - 1)


def _window_starts(points_min: np.ndarray, points_max: np.ndarray, margin: float, resolution: int):
    """Unclipped :func:`_bbox` corners of boxes (N, 2) -> (lo (N, 2), the largest width)."""
    scale = resolution / CANVAS_SIZE
    lo = np.floor((points_min - margin) * scale - 0.5).astype(np.int64)
    hi = np.ceil((points_max + margin) * scale + 0.5).astype(np.int64)
    return lo, int((hi - lo).max()) if len(lo) else 0


def _ink_entries(segments: np.ndarray, layer: np.ndarray, resolution: int):
    """Ink coverage of (M, 4) segments, each in its frame `layer` (M,), maxed per layer and pixel.

    Returns (layer, flat pixel, coverage) of every covered pixel, sorted by layer then pixel.
    """
    pixel = CANVAS_SIZE / resolution
    coordinate = centers(resolution)
    lo, width = _window_starts(
        np.minimum(segments[:, :2], segments[:, 2:]),
        np.maximum(segments[:, :2], segments[:, 2:]),
        INK_WIDTH / 2 + pixel,
        resolution,
    )
    cols = _windows(lo[:, 0], width, resolution)[:, None, :]
    rows = _windows(lo[:, 1], width, resolution)[:, :, None]
    x0, y0, x1, y1 = (segments[:, i, None, None] for i in range(4))
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    # segment_distance's float64 operations for all segments at once (in place where it saves a pass).
    px, py = coordinate[cols] - x0, coordinate[rows] - y0
    long = length2 > 0.0
    t = px * dx + py * dy
    t /= np.where(long, length2, 1.0)
    np.clip(t, 0.0, 1.0, out=t)
    t *= long  # a dot is not projected onto: t = 0 leaves px, py as they are
    px = px - t * dx
    py = py - t * dy
    px *= px
    py *= py
    px += py
    cover = np.sqrt(px, out=px)
    np.subtract(INK_WIDTH / 2, cover, out=cover)  # then coverage(distance, INK_WIDTH / 2, pixel), in place
    cover /= pixel
    cover += 0.5
    np.clip(cover, 0.0, 1.0, out=cover)
    hit = cover > 0.0
    key = (layer[:, None, None] * resolution * resolution + rows * resolution + cols)[hit]
    order = np.argsort(key, kind="stable")  # nearly sorted already: segments come in step order
    key = key[order]
    starts = np.r_[0, np.flatnonzero(key[1:] != key[:-1]) + 1]
    key = key[starts]
    return (
        key // (resolution * resolution),
        key % (resolution * resolution),
        np.maximum.reduceat(cover[hit][order], starts),
    )


def render_frames(
    states: np.ndarray,
    actions: np.ndarray,
    angle: float,
    resolution: int,
    steps: np.ndarray,
    segments: tuple[np.ndarray, np.ndarray] | None = None,
    board: np.ndarray | None = None,
    upright: bool = False,
) -> np.ndarray:
    """(k, R, R, 3) uint8 observations at `steps` (any order, repeats allowed) of a recorded episode, identical to
    replaying it with :class:`SceneRenderer` (``viz.episode_frames(...)[steps]``) but rendering only those frames.

    Frame t shows the ink of steps < t and the cursor at ``states[t, :2]`` (t = T: after the last step).
    `segments` is :func:`ink_segments`'s output and `board` :func:`render_board`'s, if cached (both as the canvas
    camera sees them, with `upright` too). With `upright`, the frames are the board's own view (the env's
    ``board_image``): the scene turned about the board's centre so that the board stands upright, as a
    :class:`SceneRenderer` at angle 0 draws it from :func:`upright_points`.
    """
    if resolution < 8:
        raise ValueError(f"image resolution must be at least 8 px, got {resolution}")
    states = np.asarray(states, dtype=np.float64)
    steps = np.asarray(steps, dtype=np.int64).reshape(-1)
    if len(steps) and (steps.min() < 0 or steps.max() > len(states)):
        raise IndexError(f"steps must lie in [0, {len(states)}], got {steps.min()}..{steps.max()}")
    wanted, inverse = np.unique(steps, return_inverse=True)
    k, size = len(wanted), resolution * resolution
    if board is None:
        board = render_board(resolution, 0.0 if upright else angle)
    # Ink: a step's segments appear from the first wanted frame after it on; frames are built in order.
    seg, seg_step = ink_segments(states, actions) if segments is None else segments
    if upright:
        seg = upright_points(np.asarray(seg, dtype=np.float64).reshape(-1, 2), angle).reshape(-1, 4)
    layer = np.searchsorted(wanted, seg_step, side="right")
    used = layer < k
    if used.any():
        layer, pixels, cover = _ink_entries(np.asarray(seg, dtype=np.float64)[used], layer[used], resolution)
    else:
        layer, pixels, cover = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    bounds = np.searchsorted(layer, np.arange(k + 1))
    board = board.reshape(size, 3)
    ink = np.zeros(size)
    canvas = np.rint(board).astype(np.uint8)  # as SceneRenderer.canvas, flat
    frames = np.empty((k, resolution, resolution, 3), dtype=np.uint8)
    for m in range(k):
        p = pixels[bounds[m] : bounds[m + 1]]
        if len(p):
            c = np.maximum(ink[p], cover[bounds[m] : bounds[m + 1]])
            ink[p] = c
            image = board[p] * (1.0 - c[:, None])  # as _blend
            image += c[:, None] * np.asarray(INK_RGB, dtype=np.float64)
            canvas[p] = np.rint(image).astype(np.uint8)
        frames[m] = canvas.reshape(resolution, resolution, 3)
    # Cursor, as SceneRenderer.frame.
    cursor = states[np.minimum(wanted, len(states) - 1), :2]
    if k and wanted[-1] == len(states):
        cursor[-1] = physics.control_step(states[-1], np.asarray(actions[-1], dtype=np.float64))[0][:2]
    if upright:
        cursor = upright_points(cursor, angle)
    pixel = CANVAS_SIZE / resolution
    outer = CURSOR_RADIUS + CURSOR_OUTLINE_WIDTH
    lo, width = _window_starts(cursor, cursor, outer + pixel, resolution)
    coordinate = centers(resolution)
    cols = _windows(lo[:, 0], width, resolution)[:, None, :]
    rows = _windows(lo[:, 1], width, resolution)[:, :, None]
    dist = np.hypot(coordinate[cols] - cursor[:, 0, None, None], coordinate[rows] - cursor[:, 1, None, None])
    index = (np.arange(k)[:, None, None], rows, cols)
    patch = frames[index].astype(np.float64)
    _blend(patch, coverage(dist, outer, pixel), CURSOR_OUTLINE_RGB)
    _blend(patch, coverage(dist, CURSOR_RADIUS, pixel), CURSOR_RGB)
    frames[index] = np.rint(patch).astype(np.uint8)
    if len(steps) == k and np.array_equal(wanted, steps):
        return frames
    return frames[inverse]
