"""The Chamfer score a lab would measure: from a photo of the board, rectified through the canvas's four markers.

In simulation the pen's ink is known exactly (:func:`bpp.benchmarks.draw3d.demonstrator.ink_chamfer`); on a real
whiteboard only a camera sees it. :func:`photo_chamfer` does what a lab would: fold the arm out of the view,
photograph the board with the fixed scene camera, find the canvas pose from the red markers
(:func:`bpp.drawing.marked_canvas.canvas_pose`), resample the photo onto DrawAnything's canvas through that pose
(one pixel of DrawAnything's 350-px board is 0.66 mm of the drawing area), take the dark pixels as ink, widen them by
DrawAnything's pen (its ink masks are 12 px wide lines) and score them against the drawing with DrawAnything's
Chamfer. ``bench/draw3d_demonstrator.py`` measures how far it is from the exact score.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from bpp.benchmarks.draw3d.dataset import ASIDE
from bpp.benchmarks.draw3d.scene import BOARD
from bpp.drawing.geometry import CANVAS_SIZE, canvas_to_unit, unit_to_canvas
from bpp.drawing.marked_canvas import CANVAS_SIDE, MARKER_SIDE, canvas_pose, drawing_to_canvas
from bpp.drawing.metric import chamfer_distance, ink_mask

INK_THRESHOLD = 128
"""A resampled pixel whose brightest channel is under this is ink: the paper is about 235, the pen's ink about 27 and
a red marker's red channel about 200."""
EDGE_MARGIN = 0.003
"""Metres inside the canvas's edge where ink is looked for: the edge's own pixels mix paper with the board."""
PEN_RADIUS_PX = 4.0
"""The photo's ink is widened by this many of DrawAnything's canvas pixels: a line about 3.5 px wide in the photo then
covers about the 12 px DrawAnything's pen inks."""


@functools.cache
def _canvas_plane() -> np.ndarray:
    """(512, 512, 2) the canvas-frame point (m) under each of DrawAnything's canvas pixel centres (computed once;
    read-only)."""
    rows, cols = np.mgrid[0:CANVAS_SIZE, 0:CANVAS_SIZE].astype(np.float64)
    unit = canvas_to_unit(np.stack([cols, rows], axis=-1).reshape(-1, 2), 0.0)
    plane = drawing_to_canvas(unit).reshape(CANVAS_SIZE, CANVAS_SIZE, 2)
    plane.flags.writeable = False
    return plane


def rectify(photo: np.ndarray, intrinsics: np.ndarray, T_camera_canvas: np.ndarray) -> np.ndarray:
    """(512, 512, 3) uint8: the photo resampled onto DrawAnything's canvas (its unit drawing square on the 350-px board
    at the centre), through the canvas pose `T_camera_canvas` and the camera's pinhole `intrinsics`."""
    # OpenCV: the iphumi extra
    import cv2

    plane = _canvas_plane()
    shape = plane.shape[:2]
    pixels = intrinsics @ (T_camera_canvas[:3, :2] @ plane.reshape(-1, 2).T + T_camera_canvas[:3, 3:4])
    u = (pixels[0] / pixels[2]).reshape(shape).astype(np.float32)
    v = (pixels[1] / pixels[2]).reshape(shape).astype(np.float32)
    return cv2.remap(photo, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def photo_ink_mask(rectified: np.ndarray) -> np.ndarray:
    """Boolean (512, 512): the rectified photo's ink on the canvas's paper (not its edge, not its red markers),
    widened to DrawAnything's pen."""
    plane = np.abs(_canvas_plane())
    paper = (plane.max(axis=-1) < CANVAS_SIDE / 2 - EDGE_MARGIN) & (
        plane.min(axis=-1) < CANVAS_SIDE / 2 - MARKER_SIDE - EDGE_MARGIN
    )
    dark = (rectified.max(axis=-1) < INK_THRESHOLD) & paper
    if not dark.any():
        return dark
    return ndimage.distance_transform_edt(~dark) <= PEN_RADIUS_PX


def photograph_canvas(scene, photo_size: int = 640) -> np.ndarray:
    """(512, 512, 3) uint8: `scene`'s canvas as a lab would photograph it once a rollout has ended (the arm folded
    away, the scene camera, the canvas pose from the markers), rectified onto DrawAnything's canvas: upright, as a
    prompt's ink is drawn (:class:`bpp.drawing.marked_canvas.CanvasNotFound` if the markers do not give the pose).
    The arm stays folded."""
    scene.fold(ASIDE)
    photo = scene.render("scene", photo_size)
    intrinsics = scene.camera_intrinsics("scene", photo_size)
    camera = scene.camera_pose("scene")
    return rectify(photo, intrinsics, canvas_pose(photo, intrinsics, up=camera[:3, :3].T @ BOARD[:, 1]))


def rectified_chamfer(rectified: np.ndarray, drawing_strokes) -> float:
    """DrawAnything's Chamfer (px) of the ink in a rectified photo (:func:`photograph_canvas`) against
    `drawing_strokes` (unit square)."""
    target = ink_mask([unit_to_canvas(np.asarray(s), 0.0) for s in drawing_strokes])
    return chamfer_distance(target, photo_ink_mask(rectified))


def photo_chamfer(scene, drawing_strokes, photo_size: int = 640) -> float:
    """DrawAnything's Chamfer (px) of the ink on `scene`'s canvas against `drawing_strokes` (unit square), measured
    from a scene-camera photo with the arm folded away, as a lab would
    (:class:`bpp.drawing.marked_canvas.CanvasNotFound` if the markers do not give the canvas pose). The arm stays
    folded: call it once a rollout has ended."""
    return rectified_chamfer(photograph_canvas(scene, photo_size), drawing_strokes)
