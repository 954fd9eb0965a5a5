"""The drawing canvas's pose from one RGB image, as on DrawAnything-Real: a square canvas with a red square marker in
each corner hangs anywhere on a large whiteboard, rotated within +-45 degrees of upright (which is what makes four
identical markers' order unambiguous). The markers give the canvas pose in the camera frame (``cv2.solvePnP``,
IPPE, with the camera intrinsics), a fixed camera-to-robot extrinsic gives it in the robot's base frame.

Frames: the canvas frame has its origin at the canvas centre, x right and y up in the board plane (for the upright
canvas), z out of the board toward the viewer; the camera frame is OpenCV's (x right, y down, z forward). Metres.
Poses are 4x4 homogeneous, ``T_a_b`` maps points in frame b to frame a.

Marker reference points are the markers' centres, measured in the image as the centroid of the marker's redness
(see :func:`find_markers` for why not a corner). A detection that does not fit the layout (a marker missing, partly
hidden or out of view, other red blobs, a poor fit) raises :class:`CanvasNotFound` saying what was seen, never a
silently wrong pose. :func:`render_canvas` draws exact synthetic photos for tests and benchmarks.
Needs OpenCV, which the ``iphumi`` extra installs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bpp.errors import UserError, require_extra

CANVAS_SIDE = 0.30
"""Side of the square drawing canvas, metres."""
MARKER_SIDE = 0.025
"""Side of each red square marker, metres; a marker's outer corner is the canvas corner."""
RED = (200, 30, 30)
"""The markers' nominal RGB."""
CANVAS_RGB = (236, 236, 230)
"""The canvas's off-white (render_canvas)."""
BOARD_RGB = (214, 218, 216)
"""The whiteboard around the canvas (render_canvas's default background)."""
OCCLUDER_RGB = (70, 70, 70)
"""Dark grey of render_canvas's occluder polygon (an arm, a hand, a pen in front of the canvas)."""
MARKER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")
"""The markers in canvas order, as seen on the upright canvas."""
DRAW_SIDE = CANVAS_SIDE - 2 * (MARKER_SIDE + 0.01)
"""The square a drawing's unit square is mapped to, inside the markers (m)."""

# Segmentation: red hue (OpenCV's 8-bit hue is 0..179), saturated, not dark. Saturation and hue do not change when
# the light gets brighter or dimmer, so only the darkness floor depends on the exposure.
HUE_MAX, SATURATION_MIN, VALUE_MIN = 12, 100, 40
MIN_MARKER_PX = 16
"""A red blob smaller than this (pixels) is noise, not a marker (a marker is ~15x15 px at 1 m with f = 600 px)."""
MIN_SOLIDITY = 0.85
"""A marker's blob fills at least this much of its convex hull (a projected square fills all of it)."""
MAX_ASPECT = 3.0
"""A marker's blob's minimum-area rectangle is at most this elongated (a square tilted 60 degrees away gives 2)."""
AREA_RATIO_RANGE = (0.9, 1.1)
"""Each marker's measured red area over the area its square projects to under the fitted pose; outside this, the
marker is partly hidden (or merged with other red) and its centroid cannot be trusted."""
MAX_REPROJECTION_PX = 1.0
"""Largest distance (pixels) between a measured marker centre and the fitted pose's projection of it."""
AMBIGUOUS_DEG = 0.5
"""A canvas turned within this of 45 degrees from upright is refused: its top and its side are equally near up, and
the markers are identical (beyond 45 degrees its top is the side nearer up: 50 degrees reads as -40)."""
SUPERSAMPLE = 4
"""render_canvas's samples per pixel along each axis."""
NOISE_STD = 2.0
"""render_canvas's pixel noise (grey levels), when given a random generator."""


class CanvasNotFound(UserError):
    """The image does not show the canvas's four red markers clearly enough for a trustworthy pose; the message says
    what was seen. `reason` is a short fixed label for counting failures: ``missing marker``, ``extra red``,
    ``partly hidden``, ``poor fit``, ``facing away`` or ``ambiguous rotation``."""

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason


def _cv2():
    return require_extra("cv2", "iphumi")


@dataclass(frozen=True)
class CanvasLayout:
    """The physical canvas: a square of side `side` (m) with a red square of side `marker_side` in each corner."""

    side: float = CANVAS_SIDE
    marker_side: float = MARKER_SIDE

    def __post_init__(self):
        if not (math.isfinite(self.side) and self.side > 0):
            raise UserError(f"canvas side must be a positive length in metres, got {self.side!r}")
        if not (math.isfinite(self.marker_side) and 0 < self.marker_side < self.side / 2):
            raise UserError(
                f"marker side must be positive and under half the canvas side ({self.side / 2} m), "
                f"got {self.marker_side!r}"
            )

    def marker_points(self) -> np.ndarray:
        """(4, 3) the markers' centres in the canvas frame, in canvas order (top-left, top-right, bottom-right,
        bottom-left): the 3-D points PnP uses."""
        h = self.side / 2 - self.marker_side / 2
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    def marker_corners(self) -> np.ndarray:
        """(4, 4, 3) each marker's square (corners in the same turning order as the markers) in the canvas frame."""
        d = self.marker_side / 2
        square = np.array([[-d, d, 0.0], [d, d, 0.0], [d, -d, 0.0], [-d, -d, 0.0]])
        return self.marker_points()[:, None, :] + square[None]

    def canvas_corners(self) -> np.ndarray:
        """(4, 3) the canvas's corners in the canvas frame, in canvas order."""
        h = self.side / 2
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


# ---------------------------------------------------------------------------------------------------------- helpers


def drawing_to_canvas(points: np.ndarray) -> np.ndarray:
    """A drawing's unit-square points (N, 2), y up -> canvas-frame points (N, 2), metres."""
    return (np.asarray(points, dtype=np.float64) - 0.5) * DRAW_SIDE


def canvas_to_drawing(points: np.ndarray) -> np.ndarray:
    """The inverse of :func:`drawing_to_canvas`."""
    return np.asarray(points, dtype=np.float64) / DRAW_SIDE + 0.5


def _intrinsics(intrinsics) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise UserError(f"intrinsics must be a finite 3x3 pinhole matrix with fx, fy > 0, got {k.tolist()}")
    return k


def _pose(pose, name: str) -> np.ndarray:
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise UserError(f"{name} must be a finite 4x4 homogeneous pose, got shape {t.shape}")
    if not np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-6) or np.linalg.det(t[:3, :3]) < 0:
        raise UserError(f"{name}'s upper-left 3x3 block must be a rotation matrix")
    return t


def _image(image) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8 or min(image.shape[:2]) < 8:
        raise UserError(f"image must be an (H, W, 3) uint8 RGB array, got {image.dtype} {image.shape}")
    return image


def _project(pose: np.ndarray, k: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 3) points in the posed frame -> (..., 2) pixels (pixel centres at integers)."""
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    return (cam @ k.T)[..., :2] / cam[..., 2:3]


def _polygon_area_centroid(polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., N, 2) simple polygons -> (...) unsigned areas and (..., 2) area centroids (shoelace formula)."""
    p, q = polygons, np.roll(polygons, -1, axis=-2)
    cross = p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1]
    area = cross.sum(-1) / 2
    centroid = ((p + q) * cross[..., None]).sum(-2) / (6 * area[..., None])
    return np.abs(area), centroid


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    return pose


# -------------------------------------------------------------------------------------------------------- detection


@dataclass(frozen=True)
class _Blob:
    centre: np.ndarray  # (2,) redness centroid, pixels
    area: float  # red area, pixels, with sub-pixel edges


def _redness(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 R - max(G, B): linear in how much of a pixel a red marker covers against any grey or white."""
    rgb = image.astype(np.float32)
    return rgb[..., 0] - np.maximum(rgb[..., 1], rgb[..., 2])


def _measure(redness: np.ndarray, labels: np.ndarray, label: int, box) -> _Blob | None:
    """Sub-pixel centroid and area of component `label` (bounding box `box` = x, y, w, h) from the redness around
    it: background-subtracted, normalised by the marker's own inside level, so independent of the exposure."""
    cv2 = _cv2()
    x, y, w, h = box
    pad = 6
    y0, y1 = max(y - pad, 0), min(y + h + pad, labels.shape[0])
    x0, x1 = max(x - pad, 0), min(x + w + pad, labels.shape[1])
    sub = labels[y0:y1, x0:x1]
    own = (sub == label).astype(np.uint8)
    others = (sub > 0) & (sub != label)
    kernel = np.ones((3, 3), np.uint8)
    region = cv2.dilate(own, kernel, iterations=2).astype(bool) & ~others  # the soft edge lies within 1-2 px
    ring = cv2.dilate(own, kernel, iterations=5).astype(bool) & ~region & ~others
    inside = cv2.erode(own, kernel).astype(bool)
    values = redness[y0:y1, x0:x1]
    # a bluish surround (a whiteboard beside the paper) has negative redness: it is no red at all, and subtracting it
    # would count every surrounding pixel of the region as part red
    background = max(float(np.median(values[ring])), 0.0) if ring.any() else 0.0
    level = float(np.median(values[inside if inside.any() else own.astype(bool)])) - background
    if level <= 0:
        return None
    weight = np.clip(values - background, 0, None) * region
    total = float(weight.sum())
    ys, xs = np.mgrid[y0:y1, x0:x1]
    centre = np.array([(weight * xs).sum() / total, (weight * ys).sum() / total])
    return _Blob(centre=centre, area=total / level)


def _detect(image: np.ndarray) -> list[_Blob]:
    """The four markers' blobs in canvas order as they appear in the image (see find_markers)."""
    cv2 = _cv2()
    image = _image(image)
    hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)
    hue, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    mask = ((hue <= HUE_MAX) | (hue >= 180 - HUE_MAX)) & (sat >= SATURATION_MIN) & (val >= VALUE_MIN)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    redness = _redness(image)
    height, width = mask.shape
    blobs, rejected = [], {"cut by the image border": 0, "not marker-shaped": 0}
    for label in range(1, count):
        x, y, w, h, area = (int(v) for v in stats[label])
        if area < MIN_MARKER_PX:
            continue
        if x == 0 or y == 0 or x + w == width or y + h == height:
            rejected["cut by the image border"] += 1
            continue
        own = (labels[y : y + h, x : x + w] == label).astype(np.uint8)
        contours, _ = cv2.findContours(own, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        contour = max(contours, key=cv2.contourArea)
        hull = cv2.convexHull(contour)
        (_, _), (rw, rh), _ = cv2.minAreaRect(contour)
        # the hull in pixels: a polygon through boundary pixels' centres misses half a pixel all round
        solidity = area / (cv2.contourArea(hull) + cv2.arcLength(hull, True) / 2 + 1)
        if solidity < MIN_SOLIDITY or max(rw, rh) > MAX_ASPECT * max(min(rw, rh), 1.0):
            rejected["not marker-shaped"] += 1
            continue
        blob = _measure(redness, labels, label, (x, y, w, h))
        if blob is None:  # no redder than its surroundings
            rejected["not marker-shaped"] += 1
            continue
        blobs.append(blob)
    if len(blobs) < 4:
        seen = "no red marker" if not blobs else f"{len(blobs)} of the 4 red markers"
        why = "; ".join(f"{n} red blob{'s' * (n > 1)} {what}" for what, n in rejected.items() if n)
        raise CanvasNotFound(
            f"found {seen} ({4 - len(blobs)} hidden or out of view{'; ' + why if why else ''}): the canvas needs "
            "all four in view",
            "missing marker",
        )
    if len(blobs) > 4:
        raise CanvasNotFound(
            f"found {len(blobs)} red marker-like blobs, expected the canvas's 4: other red things in view, or a "
            "marker split in two by something in front of it",
            "extra red",
        )
    return [blobs[i] for i in _canvas_order(np.array([b.centre for b in blobs]))]


def _canvas_order(centres: np.ndarray) -> np.ndarray:
    """Indices putting (4, 2) image points in canvas order: by angle about their centroid, the cyclic shift nearest
    the upright canvas's angles (top-left at 135 degrees, image y pointing down)."""
    d = centres - centres.mean(0)
    angle = np.arctan2(-d[:, 1], d[:, 0])
    clockwise = np.argsort(-angle)  # as seen on screen: top-left, top-right, bottom-right, bottom-left
    nominal = np.radians([135.0, 45.0, -45.0, -135.0])

    def cost(shift: int) -> float:
        dev = angle[np.roll(clockwise, -shift)] - nominal
        return float(np.sum((np.angle(np.exp(1j * dev))) ** 2))

    return np.roll(clockwise, -min(range(4), key=cost))


def find_markers(image: np.ndarray) -> np.ndarray:
    """(4, 2) float64 pixel coordinates of the four markers' centres in canvas order (top-left, top-right,
    bottom-right, bottom-left of the canvas as it appears upright in the image), from an (H, W, 3) uint8 RGB image.

    Red pixels are segmented in HSV (red hue, saturation >= 100, value >= 40: hue and saturation do not change with
    the brightness of the light); connected components smaller than a marker are dropped, and ones touching the image
    border, not convex or elongated are rejected. Exactly four must remain, else :class:`CanvasNotFound`. They are
    ordered by angle about their centroid, which names them correctly for canvases within +-45 degrees of upright
    in the image (:func:`canvas_pose` settles the order in 3-D instead, where perspective does not skew angles).

    Sub-pixel refinement: each marker's reference point is the centroid of its redness, R - max(G, B) less the
    surrounding background, over the blob and a 2-px margin. Redness is linear in how much of a pixel the marker
    covers, so the centroid is the area centroid of the marker's image: it averages all of a marker's pixels (not
    the dozen next to one corner), does not depend on the segmentation threshold, and is unchanged by symmetric blur
    or defocus, all of which move a corner found by ``cv2.cornerSubPix`` or a contour. Partial occlusion moves it
    by at most the hidden fraction times the marker's size, and :func:`canvas_pose` measures that fraction and
    refuses a marker with more than a little hidden (a small nick at a corner instead moves a corner by its whole
    size, unnoticed). Its one bias is perspective (the image of a square's centre is not the centre of its image:
    under 0.1 px here), which :func:`canvas_pose` removes with the fitted pose; a brightness gradient across a
    marker shifts it a little too (0.03 px for a 30 % gradient across a 640-px image).
    """
    return np.array([b.centre for b in _detect(image)])


# ------------------------------------------------------------------------------------------------------------- pose


def _solve(k: np.ndarray, obj: np.ndarray, pts: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Planar PnP: IPPE's two solutions, the better one in front of the camera and facing it, refined by
    Levenberg-Marquardt (or only the refinement, from `start`)."""
    cv2 = _cv2()
    if start is None:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, pts, k, None, flags=cv2.SOLVEPNP_IPPE)
        for rvec, tvec in sorted(zip(rvecs, tvecs, strict=True), key=lambda rt: _reprojection(k, obj, pts, *rt)):
            rotation = cv2.Rodrigues(rvec)[0]
            if tvec[2, 0] > 0 and rotation[:, 2] @ tvec[:, 0] < 0:
                break
        else:
            raise CanvasNotFound(
                "the red markers only fit a canvas behind the camera or facing away from it", "facing away"
            )
    else:
        rvec, tvec = cv2.Rodrigues(start[:3, :3])[0], start[:3, 3:].copy()
    rvec, tvec = cv2.solvePnPRefineLM(obj, pts, k, None, rvec, tvec)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(rvec)[0], tvec[:, 0]
    return pose


def _reprojection(k, obj, pts, rvec, tvec) -> float:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = _cv2().Rodrigues(rvec)[0], np.ravel(tvec)
    return float(np.abs(_project(pose, k, obj) - pts).max())


def _quarter_rotations(pose: np.ndarray, up: np.ndarray) -> int:
    """How many 90-degree rotations about its normal bring the canvas's y axis within 45 degrees of `up` (a direction in
    the camera frame) projected onto the canvas plane. :class:`CanvasNotFound` within ``AMBIGUOUS_DEG`` of 45
    degrees, where two of them are as near."""
    up_canvas = pose[:3, :3].T @ up
    if math.hypot(up_canvas[0], up_canvas[1]) < 1e-6:  # the canvas faces straight up or down: no upright
        return 0
    quarters = math.atan2(up_canvas[0], up_canvas[1]) / (math.pi / 2)
    turned = 90.0 * (quarters - round(quarters))  # the canvas's turn from the nearest upright, degrees
    if abs(abs(turned) - 45.0) < AMBIGUOUS_DEG:
        raise CanvasNotFound(
            f"the canvas is turned {abs(turned):.1f} degrees from upright: within {AMBIGUOUS_DEG:g} degree of 45, its "
            "four identical markers cannot tell its top from its side; hang it nearer upright",
            "ambiguous rotation",
        )
    return round(quarters)


def canvas_pose(
    image: np.ndarray, intrinsics, layout: CanvasLayout = CanvasLayout(), *, up: np.ndarray | None = None
) -> np.ndarray:
    """(4, 4) T_camera_canvas from an (H, W, 3) uint8 RGB image and the (3, 3) camera intrinsics (an undistorted
    image: pinhole model, no lens distortion).

    The markers of :func:`find_markers` are fitted by ``cv2.solvePnPGeneric`` (SOLVEPNP_IPPE; of its two planar
    solutions, the better one in front of the camera and facing it), refined by Levenberg-Marquardt, refitted twice with
    each measured centroid corrected by the fitted pose's perspective bias (the centroid of the marker's projected
    square minus the projection of its centre). The order is then settled in 3-D: the canvas's y axis is the one
    of its four 90-degree rotations within 45 degrees of `up` (the board's upward direction in the camera frame, by
    default the camera's own up, -y) projected onto the canvas plane, which perspective does not distort as it does
    angles in the image.

    Raises :class:`CanvasNotFound` when the result cannot be trusted: a marker whose red area is outside
    ``AREA_RATIO_RANGE`` of its square's area under the pose (partly hidden, or merged with other red), or a
    measured centre farther than ``MAX_REPROJECTION_PX`` from its fitted projection.
    """
    k = _intrinsics(intrinsics)
    up = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) == 0:
        raise UserError(f"up must be a nonzero direction (3,) in the camera frame, got {up.tolist()}")
    blobs = _detect(image)
    obj = layout.marker_points()
    measured = np.array([b.centre for b in blobs])
    pose = _solve(k, obj, measured)
    quarters = _quarter_rotations(pose, up)
    if quarters:
        # shifting the labels by one marker rotates the canvas frame 90 degrees about its normal (a square)
        blobs, measured = blobs[quarters:] + blobs[:quarters], np.roll(measured, -quarters, axis=0)
        pose = _solve(k, obj, measured, pose @ _rot_z(-quarters * math.pi / 2))
    squares = layout.marker_corners()
    for _ in range(2):
        _, centroids = _polygon_area_centroid(_project(pose, k, squares))
        corrected = measured - (centroids - _project(pose, k, obj))
        pose = _solve(k, obj, corrected, pose)

    areas, _ = _polygon_area_centroid(_project(pose, k, squares))
    for name, blob, area in zip(MARKER_NAMES, blobs, areas, strict=True):
        ratio = blob.area / area
        if not AREA_RATIO_RANGE[0] <= ratio <= AREA_RATIO_RANGE[1]:
            what, reason = ("partly hidden", "partly hidden") if ratio < 1 else ("merged with other red", "extra red")
            raise CanvasNotFound(
                f"the {name} red marker looks {what}: its red area is {ratio:.0%} of what the canvas pose predicts "
                f"(expected {AREA_RATIO_RANGE[0]:.0%}-{AREA_RATIO_RANGE[1]:.0%})",
                reason,
            )
    error = np.linalg.norm(_project(pose, k, obj) - corrected, axis=1)
    if error.max() > MAX_REPROJECTION_PX:
        name = MARKER_NAMES[int(error.argmax())]
        raise CanvasNotFound(
            f"the red markers do not fit a {layout.side} m square canvas: the {name} one is {error.max():.1f} px "
            f"from where the best fit puts it (at most {MAX_REPROJECTION_PX} px); check the intrinsics and layout",
            "poor fit",
        )
    return pose


def canvas_in_base(T_base_camera: np.ndarray, T_camera_canvas: np.ndarray) -> np.ndarray:
    """(4, 4) T_base_canvas: the canvas pose in the robot's base frame, through the fixed camera extrinsic."""
    return _pose(T_base_camera, "T_base_camera") @ _pose(T_camera_canvas, "T_camera_canvas")


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(position error in m, rotation error in degrees) between two (4, 4) poses of the same frame."""
    est, true = np.asarray(T_est, dtype=np.float64), np.asarray(T_true, dtype=np.float64)
    delta = est[:3, :3].T @ true[:3, :3]
    sin = np.linalg.norm([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]]) / 2
    cos = (np.trace(delta) - 1) / 2
    return float(np.linalg.norm(est[:3, 3] - true[:3, 3])), math.degrees(math.atan2(sin, cos))


# -------------------------------------------------------------------------------------------------------- rendering


def render_canvas(
    T_camera_canvas: np.ndarray,
    intrinsics,
    size: tuple[int, int] = (640, 480),
    *,
    light: float = 1.0,
    occluder: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
    background: np.ndarray | None = None,
    layout: CanvasLayout = CanvasLayout(),
) -> np.ndarray:
    """(H, W, 3) uint8 RGB synthetic photo (`size` is (W, H)) of the canvas at `T_camera_canvas` on a whiteboard.

    The canvas (off-white) and its markers (RED) are drawn exactly: each pixel is the average of SUPERSAMPLE^2
    samples mapped onto the canvas plane through the inverse homography, so a marker's image has the true area
    centroid. `occluder`, an (N, 2) polygon in pixels, is drawn over it in dark grey (anti-aliased). `light`
    scales the brightness; with `rng`, a random brightness gradient across the image (+-30 %) and pixel noise
    (NOISE_STD grey levels) are added. `background` replaces the plain whiteboard with an (H, W, 3) uint8 image.
    """
    cv2, k, pose = _cv2(), _intrinsics(intrinsics), _pose(T_camera_canvas, "T_camera_canvas")
    w, h = size
    if background is None:
        frame = np.empty((h, w, 3), np.float32)
        frame[:] = BOARD_RGB
    else:
        frame = np.array(background, dtype=np.float32)
        if frame.shape != (h, w, 3) or np.asarray(background).dtype != np.uint8:
            raise UserError(f"background must be an ({h}, {w}, 3) uint8 image, got {np.asarray(background).shape}")
    corners = layout.canvas_corners() @ pose[:3, :3].T + pose[:3, 3]
    if np.any(corners[:, 2] <= 1e-3):
        raise UserError("the canvas must lie wholly in front of the camera (every corner at z > 0)")
    quad = (corners @ k.T)[:, :2] / corners[:, 2:]
    x0, y0 = np.maximum(np.floor(quad.min(0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(quad.max(0)).astype(int) + 2, (w, h))
    if x1 > x0 and y1 > y0:
        _draw_canvas(frame, pose, k, layout, (x0, y0, x1, y1))
    if occluder is not None:
        polygon = np.asarray(occluder, dtype=np.float64)
        if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) < 3:
            raise UserError(f"occluder must be an (N, 2) polygon in pixels with N >= 3, got shape {polygon.shape}")
        s = SUPERSAMPLE
        fine = np.zeros((h * s, w * s), np.uint8)
        cv2.fillPoly(fine, [np.rint((s * (polygon + 0.5) - 0.5) * 16).astype(np.int32)], 255, cv2.LINE_8, shift=4)
        cover = cv2.resize(fine.astype(np.float32) / 255, (w, h), interpolation=cv2.INTER_AREA)[..., None]
        frame = cover * np.float32(OCCLUDER_RGB) + (1 - cover) * frame
    gx, gy = rng.uniform(-0.3, 0.3, 2) if rng is not None else (0.0, 0.0)
    u = np.linspace(-0.5, 0.5, w, dtype=np.float32)
    v = np.linspace(-0.5, 0.5, h, dtype=np.float32)
    frame *= (light * (1 + gx * u[None, :] + gy * v[:, None]))[..., None]
    if rng is not None:
        frame += rng.standard_normal(frame.shape, dtype=np.float32) * NOISE_STD
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def _draw_canvas(frame: np.ndarray, pose: np.ndarray, k: np.ndarray, layout: CanvasLayout, box) -> None:
    """Composite the canvas and markers over `frame` (float32, in place) inside pixel box (x0, y0, x1, y1)."""
    cv2 = _cv2()
    x0, y0, x1, y1 = box
    s = SUPERSAMPLE
    to_image = k @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])  # canvas plane (x, y, 1) -> pixels
    to_plane = np.linalg.inv(to_image).astype(np.float32)
    # sample j of pixel u sits at u + (j + 0.5) / s - 0.5 (pixel centres at integers)
    us = (np.arange(s * x0, s * x1, dtype=np.float32) + 0.5) / s - 0.5
    vs = (np.arange(s * y0, s * y1, dtype=np.float32) + 0.5) / s - 0.5
    uu, vv = us[None, :], vs[:, None]
    depth = to_plane[2, 0] * uu + to_plane[2, 1] * vv + to_plane[2, 2]
    x = np.abs((to_plane[0, 0] * uu + to_plane[0, 1] * vv + to_plane[0, 2]) / depth)
    y = np.abs((to_plane[1, 0] * uu + to_plane[1, 1] * vv + to_plane[1, 2]) / depth)
    half, inner = layout.side / 2, layout.side / 2 - layout.marker_side
    on_canvas = (depth > 0) & (x <= half) & (y <= half)
    on_marker = on_canvas & (x >= inner) & (y >= inner)
    size = (x1 - x0, y1 - y0)  # INTER_AREA by a whole factor averages each pixel's s x s samples
    marker = cv2.resize(on_marker.astype(np.float32), size, interpolation=cv2.INTER_AREA)[..., None]
    canvas = cv2.resize(on_canvas.astype(np.float32), size, interpolation=cv2.INTER_AREA)[..., None] - marker
    under = frame[y0:y1, x0:x1]
    frame[y0:y1, x0:x1] = marker * np.float32(RED) + canvas * np.float32(CANVAS_RGB) + (1 - marker - canvas) * under


def canvas_placement(
    position, *, tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0, rotation_deg: float = 0.0
) -> np.ndarray:
    """(4, 4) T_camera_canvas with the canvas centre at `position` (3,) in the camera frame, its normal tilted by
    `tilt_deg` from pointing straight back at the camera (toward image direction `tilt_axis_deg`, 0 = right, 90 =
    down), and rotated by `rotation_deg` about its normal from upright as :func:`canvas_pose` defines it (y along
    the camera's up projected onto the canvas plane); positive is counterclockwise as the camera sees it."""
    tilt, axis = math.radians(tilt_deg), math.radians(tilt_axis_deg)
    normal = -np.array([math.sin(tilt) * math.cos(axis), math.sin(tilt) * math.sin(axis), math.cos(tilt)])
    up = np.array([0.0, -1.0, 0.0])
    up = up - (up @ normal) * normal
    up /= np.linalg.norm(up)
    theta = math.radians(rotation_deg)
    y_axis = math.cos(theta) * up + math.sin(theta) * np.cross(normal, up)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([np.cross(y_axis, normal), y_axis, normal])
    pose[:3, 3] = position
    return pose


def random_canvas_pose(
    rng: np.random.Generator,
    intrinsics,
    size: tuple[int, int] = (640, 480),
    *,
    distance: tuple[float, float] = (0.5, 1.0),
    max_tilt_deg: float = 30.0,
    max_rotation_deg: float = 45.0,
    margin_px: float = 8.0,
    layout: CanvasLayout = CanvasLayout(),
) -> np.ndarray:
    """(4, 4) a random :func:`canvas_placement` wholly in view (`margin_px` from the image border): centre
    `distance` m from the camera, tilted up to `max_tilt_deg` (uniformly over that cap of directions), rotated
    within `max_rotation_deg` of upright."""
    k = _intrinsics(intrinsics)
    w, h = size
    for _ in range(1000):
        ray = np.linalg.solve(k, np.r_[rng.uniform((0.15 * w, 0.15 * h), (0.85 * w, 0.85 * h)), 1.0])
        pose = canvas_placement(
            rng.uniform(*distance) * ray / np.linalg.norm(ray),
            tilt_deg=math.degrees(math.acos(1 - rng.uniform() * (1 - math.cos(math.radians(max_tilt_deg))))),
            tilt_axis_deg=rng.uniform(0, 360),
            rotation_deg=rng.uniform(-max_rotation_deg, max_rotation_deg),
        )
        quad = _project(pose, k, layout.canvas_corners())
        if np.all(quad >= margin_px) and np.all(quad <= (w - 1 - margin_px, h - 1 - margin_px)):
            return pose
    raise UserError(f"no canvas placement at {distance} m fits in a {w}x{h} image with these intrinsics")
