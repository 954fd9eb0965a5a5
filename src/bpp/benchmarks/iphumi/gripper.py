"""Gripper width from the phone's ultrawide camera: two ArUco tags (DICT_4X4_50, 16 mm) on the gripper's fingers.

Each tag's pose comes from ``cv2.solvePnP`` (IPPE_SQUARE) with the recording's ultrawide intrinsics; the raw width is
the distance along the camera's x axis between the two tag centres, ``x(second id) - x(first id)``, as in iPhUMI's
own processing. A gripper-calibration recording (opened and closed a few times) gives the range of that width and a
linear map predicting one tag's x from the other's, used when a finger's tag is hidden. A demonstration's width is
clipped to the range, shifted so that 0 is closed, and interpolated over the frames where it could not be measured.
Needs the ``iphumi`` extra (OpenCV).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from bpp.errors import UserError, require_extra

TAG_SIZE_M = 0.016
"""Side of a tag's black square, metres (the white quiet zone around it is extra)."""
TAG_IDS = {"right": (0, 1), "left": (6, 7)}
"""Tag ids (first, second) on the fingers of each side's gripper; a single gripper is ``right``."""
DEPTH_RANGE_M = (0.03, 0.3)
"""Tags whose centre is nearer or farther than this along the optical axis are not the phone's own fingers."""
MIN_CALIBRATION_FRAMES = 10
MIN_RANGE_M = 0.01
# The synthetic finger geometry of render_fingers, in OpenCV camera axes (x right, y down, z forward), metres: both
# tag centres at height FINGER_Y and depth FINGER_Z, at x = -width/2 (first id) and +width/2 (second id), each tag
# tilted about the camera's x axis so that it faces the camera.
FINGER_Y_M, FINGER_Z_M = 0.035, 0.10
_TAG_TILT = math.atan2(FINGER_Y_M, FINGER_Z_M)
_CELLS, _CELL_PX, _SUPERSAMPLE = 6, 40, 4  # 4x4 bits + 1 black border cell each side; source pixels per cell


def _cv2():
    return require_extra("cv2", "iphumi")


def tag_ids(side: str) -> tuple[int, int]:
    """The (first, second) tag ids on the fingers of `side`'s gripper ("right" or "left")."""
    if not isinstance(side, str) or side not in TAG_IDS:
        raise UserError(f"no gripper tags for side {side!r}: expected one of {sorted(TAG_IDS)} (a head phone has none)")
    return TAG_IDS[side]


def _intrinsics(intrinsics) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise UserError(f"intrinsics must be a finite 3x3 pinhole matrix with fx, fy > 0, got {k.tolist()}")
    return k


@functools.lru_cache(maxsize=1)
def _detector():
    cv2 = _cv2()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)


def _tag_corners(size: float) -> np.ndarray:
    """(4, 3) corners of a square of side `size` in its own frame, in ArUco's order (top-left first, clockwise)."""
    h = size / 2
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)


def detect_fingers(
    frame: np.ndarray, intrinsics, side: str, depth_range: tuple[float, float] = DEPTH_RANGE_M
) -> dict[int, np.ndarray]:
    """Tag id -> (3,) tag centre in the camera frame (metres, OpenCV axes) for `side`'s tags seen in `frame`, an
    (H, W, 3) uint8 RGB ultrawide image; a tag outside `depth_range` (or seen twice: the nearer is kept) is dropped."""
    cv2 = _cv2()
    wanted, k = tag_ids(side), _intrinsics(intrinsics)
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise UserError(f"an ultrawide frame must be an (H, W, 3) uint8 RGB image, got {frame.dtype} {frame.shape}")
    corners, ids, _ = _detector().detectMarkers(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY))
    found: dict[int, np.ndarray] = {}
    for quad, tag in zip(corners, () if ids is None else ids.ravel().tolist(), strict=True):
        if tag not in wanted:
            continue
        ok, _, tvec = cv2.solvePnP(
            _tag_corners(TAG_SIZE_M), quad.reshape(4, 2).astype(np.float64), k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        centre = tvec.reshape(3)
        if ok and depth_range[0] < centre[2] < depth_range[1] and (tag not in found or centre[2] < found[tag][2]):
            found[tag] = centre
    return found


def _check_pair(name: str, value) -> tuple[float, float]:
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        pair = ()
    if len(pair) != 2 or not all(map(math.isfinite, pair)):
        raise UserError(f"gripper calibration {name!r} must be two finite numbers [a, b], got {value!r}")
    return pair


@dataclass(frozen=True)
class GripperCalibration:
    """One gripper's width range (metres, raw tag-to-tag x distance) and the linear maps ``x1 = a + b * x0`` and
    ``x0 = a + b * x1`` between the x of its first (x0) and second (x1) tag, from `n_frames` frames showing both."""

    side: str
    min_width: float
    max_width: float
    x1_from_x0: tuple[float, float]
    x0_from_x1: tuple[float, float]
    n_frames: int

    def __post_init__(self):
        tag_ids(self.side)
        for name in ("min_width", "max_width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise UserError(f"gripper calibration {name!r} must be a finite number of metres, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not self.min_width < self.max_width:
            raise UserError(f"gripper calibration needs min_width < max_width, got {self.min_width}, {self.max_width}")
        for name in ("x1_from_x0", "x0_from_x1"):
            object.__setattr__(self, name, _check_pair(name, getattr(self, name)))
        if isinstance(self.n_frames, bool) or not isinstance(self.n_frames, int) or self.n_frames < 1:
            raise UserError(f"gripper calibration 'n_frames' must be a positive integer, got {self.n_frames!r}")

    def to_json(self) -> dict:
        """A JSON-ready dict, read back by :meth:`from_json`."""
        return {
            "side": self.side,
            "min_width": self.min_width,
            "max_width": self.max_width,
            "x1_from_x0": list(self.x1_from_x0),
            "x0_from_x1": list(self.x0_from_x1),
            "n_frames": self.n_frames,
        }

    @classmethod
    def from_json(cls, data: dict) -> GripperCalibration:
        """The calibration `data` (from :meth:`to_json`) holds; a UserError names a missing, extra or bad field."""
        keys = ("side", "min_width", "max_width", "x1_from_x0", "x0_from_x1", "n_frames")
        if not isinstance(data, dict):
            raise UserError(f"a gripper calibration must be a JSON object, got {type(data).__name__}")
        if sorted(data) != sorted(keys):
            missing, extra = sorted(set(keys) - set(data)), sorted(set(data) - set(keys))
            raise UserError(f"gripper calibration fields are {list(keys)}: missing {missing}, unexpected {extra}")
        return cls(**data)


def width_from_tags(found: dict, side: str, calibration: GripperCalibration | None = None) -> float:
    """Raw width (metres) from `found` (tag id -> (3,) centre): ``x1 - x0`` with both tags, with one tag the other
    predicted by `calibration`'s map; nan when neither tag (or one, without a calibration) is there."""
    first, second = tag_ids(side)
    if calibration is not None and calibration.side != side:
        raise UserError(f"the gripper calibration is for side {calibration.side!r}, not {side!r}")
    x = {tag: float(np.asarray(found[tag])[0]) for tag in (first, second) if tag in found}
    if len(x) == 2:
        return x[second] - x[first]
    if calibration is None or not x:
        return math.nan
    if first in x:
        a, b = calibration.x1_from_x0
        return a + b * x[first] - x[first]
    a, b = calibration.x0_from_x1
    return x[second] - (a + b * x[second])


def _fit_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(a, b) of ``y = a + b * x`` by least squares, refitted once without residuals beyond 3 MADs."""
    b, a = np.polyfit(x, y, 1)
    residual = y - (a + b * x)
    deviation = np.abs(residual - np.median(residual))
    keep = deviation <= 3 * np.median(deviation)
    if np.median(deviation) > 0 and 3 <= keep.sum() < len(x):
        b, a = np.polyfit(x[keep], y[keep], 1)
    return float(a), float(b)


def calibrate(
    frames: Iterable[np.ndarray], intrinsics, side: str, min_frames: int = MIN_CALIBRATION_FRAMES
) -> GripperCalibration:
    """Width range and tag-to-tag maps from a gripper-calibration recording's ultrawide frames (each (H, W, 3)
    uint8 RGB) in which the gripper is opened and closed; at least `min_frames` must show both tags."""
    first, second = tag_ids(side)
    pairs = []
    for frame in frames:
        found = detect_fingers(frame, intrinsics, side)
        if first in found and second in found:
            pairs.append((found[first][0], found[second][0]))
    if len(pairs) < min_frames:
        raise UserError(
            f"gripper calibration ({side}): only {len(pairs)} frames show both finger tags {first} and {second}, "
            f"need at least {min_frames}; are the tags in view of the ultrawide camera?"
        )
    x0, x1 = np.asarray(pairs, dtype=np.float64).T
    widths = x1 - x0
    if np.ptp(widths) < MIN_RANGE_M:
        raise UserError(
            f"gripper calibration ({side}): the width only spans {np.ptp(widths) * 1000:.1f} mm, need at least "
            f"{MIN_RANGE_M * 1000:.0f} mm; open and close the gripper fully during the calibration recording"
        )
    return GripperCalibration(
        side, float(widths.min()), float(widths.max()), _fit_line(x0, x1), _fit_line(x1, x0), len(pairs)
    )


def width_series(frames: Iterable[np.ndarray], intrinsics, side: str, calibration: GripperCalibration) -> np.ndarray:
    """(N,) width in metres per frame, 0 = closed: clipped to the calibrated range minus its minimum, frames
    without a measurement linearly interpolated over the frame index (held at the ends)."""
    raw = [width_from_tags(detect_fingers(frame, intrinsics, side), side, calibration) for frame in frames]
    width = np.clip(np.asarray(raw, dtype=np.float64), calibration.min_width, calibration.max_width)
    width -= calibration.min_width
    measured = np.isfinite(width)
    if not measured.any():
        raise UserError(f"no gripper width in any of the {len(width)} ultrawide frames ({side}): no finger tag seen")
    index = np.arange(len(width))
    return np.interp(index, index[measured], width[measured])


def finger_positions(width: float, side: str) -> dict[int, np.ndarray]:
    """Tag id -> (3,) tag centre (metres, camera frame) of the synthetic gripper opened to raw `width`."""
    first, second = tag_ids(side)
    return {
        first: np.array([-width / 2, FINGER_Y_M, FINGER_Z_M]),
        second: np.array([width / 2, FINGER_Y_M, FINGER_Z_M]),
    }


def _rotation(tilt: float, rng: np.random.Generator | None) -> np.ndarray:
    """Tag frame -> camera frame: facing the camera (tag y up, normal towards it), tilted up by `tilt` radians."""
    c, s = math.cos(tilt), math.sin(tilt)
    rotation = np.array([[1, 0, 0], [0, c, s], [0, -s, c]]) @ np.diag([1.0, -1.0, -1.0])
    if rng is not None:
        jitter, _ = _cv2().Rodrigues(rng.normal(0, math.radians(2), 3))
        rotation = rotation @ jitter
    return rotation


def render_fingers(
    width: float,
    intrinsics,
    side: str,
    size: tuple[int, int] = (640, 480),
    rng: np.random.Generator | None = None,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W, 3) uint8 RGB synthetic ultrawide frame (`size` is (W, H)) of the fingers' tags at
    :func:`finger_positions`; `rng` adds pose jitter that keeps each tag's x, and pixel noise."""
    cv2, k = _cv2(), _intrinsics(intrinsics)
    w, h = size
    frame = np.full((h, w, 3), 110, np.uint8) if background is None else np.array(background)
    if frame.shape != (h, w, 3) or frame.dtype != np.uint8:
        raise UserError(f"background must be an ({h}, {w}, 3) uint8 image, got {frame.dtype} {frame.shape}")
    s = _SUPERSAMPLE
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for tag, centre in finger_positions(width, side).items():
        marker = cv2.aruco.generateImageMarker(dictionary, tag, _CELLS * _CELL_PX, borderBits=1)
        source = cv2.copyMakeBorder(marker, _CELL_PX, _CELL_PX, _CELL_PX, _CELL_PX, cv2.BORDER_CONSTANT, value=255)
        if rng is not None:
            centre = centre + np.r_[0.0, rng.uniform(-0.002, 0.002, 2)]
        padded = _tag_corners(TAG_SIZE_M * (_CELLS + 2) / _CELLS) @ _rotation(_TAG_TILT, rng).T + centre
        quad = (padded @ k.T)[:, :2] / padded[:, 2:]
        x0, y0 = np.maximum(np.floor(quad.min(0)).astype(int) - 2, 0)
        x1, y1 = np.minimum(np.ceil(quad.max(0)).astype(int) + 3, (w, h))
        if x1 <= x0 or y1 <= y0:
            continue
        # supersample the region: low-res coordinate u is high-res s * (u - x0 + 0.5) - 0.5 there
        target = (s * (quad - (x0, y0) + 0.5) - 0.5).astype(np.float32)
        n = source.shape[0]
        corners = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32) - 0.5
        homography = cv2.getPerspectiveTransform(corners, target)
        shape = (s * (x1 - x0), s * (y1 - y0))
        tag_img = cv2.warpPerspective(source.astype(np.float32), homography, shape, flags=cv2.INTER_LINEAR)
        alpha = cv2.warpPerspective(np.ones_like(source, np.float32), homography, shape, flags=cv2.INTER_LINEAR)
        region = np.repeat(np.repeat(frame[y0:y1, x0:x1].astype(np.float32), s, 0), s, 1)
        region = alpha[..., None] * tag_img[..., None] + (1 - alpha[..., None]) * region
        region = cv2.resize(region, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
        frame[y0:y1, x0:x1] = np.clip(np.rint(region), 0, 255)
    if rng is not None:
        noise = rng.standard_normal(frame.shape, dtype=np.float32) * 2.0  # float32: a quarter of the time
        frame = np.clip(np.rint(frame + noise), 0, 255).astype(np.uint8)
    return frame
