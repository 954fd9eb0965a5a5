"""Pictures of drawings and demonstrations: contact sheets, stroke-order colouring, animations."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bpp.benchmarks.draw.physics import PEN_THRESHOLD, control_step
from bpp.benchmarks.draw.render import SceneRenderer, line_coverage
from bpp.drawing.geometry import BOARD_CENTER, rotation, unit_to_canvas
from bpp.drawing.raster import INK_WIDTH, polyline_segments
from bpp.media import contact_sheet, save_animation  # noqa: F401 - part of this module's interface

TARGET_RGB = (255, 80, 80)


def _paint_paths(image: np.ndarray, paths: Sequence[np.ndarray], rgb, alpha: float = 1.0) -> None:
    """Blend (N, 2) canvas polylines into a float (H, W, 3) image in place (only the pixels the lines may cover are
    measured: :func:`~bpp.benchmarks.draw.render.line_coverage`)."""
    segs = [polyline_segments(p) for p in paths if len(p)]
    if not segs:
        return
    pixels, cover = line_coverage(image.shape[0], np.concatenate(segs), INK_WIDTH / 2)
    cover = alpha * cover[:, None]
    flat = image.reshape(-1, 3)
    flat[pixels] = flat[pixels] * (1.0 - cover) + cover * np.asarray(rgb, dtype=np.float64)


def stroke_colors(n: int) -> np.ndarray:
    """(n, 3) RGB colours in drawing order (early strokes purple, late ones yellow)."""
    # matplotlib: half a second to import, for pictures only
    from matplotlib import colormaps

    return (np.asarray(colormaps["plasma"](np.linspace(0.0, 0.85, max(n, 1))))[:, :3] * 255)[:n]


def render_strokes(strokes: Sequence[np.ndarray], angle: float, size: int = 256) -> np.ndarray:
    """(size, size, 3) uint8: canvas polylines over the board, each stroke coloured by its order."""
    image = SceneRenderer(size, angle).board.copy()
    for stroke, rgb in zip(strokes, stroke_colors(len(strokes)), strict=True):
        _paint_paths(image, [stroke], rgb)
    return np.rint(image).astype(np.uint8)


def render_drawing(drawing, angle: float = 0.0, size: int = 256) -> np.ndarray:
    """A :class:`Drawing` on the board at `angle`, strokes coloured by order."""
    return render_strokes([unit_to_canvas(s, angle) for s in drawing.strokes], angle, size)


def group_strokes(states: np.ndarray, actions: np.ndarray) -> list[np.ndarray]:
    """Split a recorded episode's inked path into strokes (maximal runs of pen-down steps)."""
    strokes, current = [], []
    for state, action in zip(states, actions, strict=True):
        if action[2] > PEN_THRESHOLD:
            _, path = control_step(state, action)
            current.append(path if not current else path[1:])
        elif current:
            strokes.append(np.concatenate(current))
            current = []
    if current:
        strokes.append(np.concatenate(current))
    return strokes


def target_coverage(target_paths: Sequence[np.ndarray], angle: float, size: int) -> np.ndarray:
    """(size, size) ink coverage of upright canvas polylines rotated onto the board at `angle`."""
    center = np.asarray(BOARD_CENTER)
    layer = SceneRenderer(size, angle)
    for p in target_paths:
        layer.add_ink((np.asarray(p) - center) @ rotation(angle).T + center)
    return layer.ink


def episode_frames(states: np.ndarray, actions: np.ndarray, angle: float, size: int = 256) -> list[np.ndarray]:
    """Replay an episode into (size, size, 3) frames, one per observation, plus the final one."""
    renderer = SceneRenderer(size, angle)
    frames = []
    for state, action in zip(states, actions, strict=True):
        frames.append(renderer.frame(state[:2]))
        state, path = control_step(state, action)
        if action[2] > PEN_THRESHOLD:
            renderer.add_ink(path)
    frames.append(renderer.frame(state[:2]))
    return frames
