"""What a lab supplies for DrawAnything-Real: its fixed camera's calibration, in a file, and a check that it holds.

A calibration file is JSON::

    {
      "camera": "scene",
      "width": 640, "height": 640,
      "intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
      "distortion": [k1, k2, p1, p2, k3],
      "T_base_camera": [[...4 values...], ...4 rows...],
      "board_up": [x, y, z]
    }

``intrinsics`` is the pinhole matrix in OpenCV's convention (pixel i's centre at coordinate i; from
``cv2.calibrateCamera`` or the camera's factory calibration); ``distortion`` OpenCV's coefficients (optional: photos
are undistorted with them before the markers are found); ``T_base_camera`` the camera's pose in the robot's base frame
with OpenCV's axes (x right, y down, z forward), from a hand-eye calibration; ``board_up`` the board's upward direction
in the base frame (optional), which settles which marker is the canvas's top-left.

The check (:func:`check_calibration`) compares the canvas pose a photo gives, through the calibration, with the four
markers' centres touched by the pen tip and read from the robot's forward kinematics: the two agree to a few
millimetres when the intrinsics and the extrinsic are right. ``bpp draw3d calibration`` writes the simulated scene
camera's file, a photo and touched points (the simulator standing in for a lab), and checks a lab's own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw3d.dataset import ASIDE, PHOTO_SIZE, random_placement
from bpp.benchmarks.draw3d.scene import BOARD, Scene, canvas_transform
from bpp.drawing.marked_canvas import MARKER_NAMES, CanvasLayout, canvas_in_base, canvas_pose
from bpp.errors import UserError
from bpp.utils import read_json, write_json_atomic

TOLERANCE_MM = 5.0
"""A touched marker farther than this from where the photo and calibration put it fails the check."""


@dataclass(frozen=True)
class CameraCalibration:
    """A fixed camera's intrinsics, lens distortion and pose in the robot's base frame (see the module docstring)."""

    width: int
    height: int
    intrinsics: np.ndarray
    T_base_camera: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    board_up: np.ndarray | None = None
    camera: str = "scene"

    def __post_init__(self):
        k, pose = np.asarray(self.intrinsics, np.float64), np.asarray(self.T_base_camera, np.float64)
        problems = []
        if not (isinstance(self.width, int) and isinstance(self.height, int) and self.width > 0 and self.height > 0):
            problems.append(f"width and height must be positive pixel counts, got {self.width!r} x {self.height!r}")
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            problems.append(f"intrinsics must be a finite 3x3 matrix, got shape {k.shape}")
        elif not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], [0, 0, 1]) and k[1, 0] == 0):
            problems.append("intrinsics must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        elif not (0 <= k[0, 2] < self.width and 0 <= k[1, 2] < self.height):
            where = f"({k[0, 2]:g}, {k[1, 2]:g})"
            problems.append(f"the principal point {where} is outside the {self.width}x{self.height} image")
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            problems.append(f"T_base_camera must be a finite 4x4 matrix, got shape {pose.shape}")
        else:
            rotation = pose[:3, :3]
            if not (np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) and np.linalg.det(rotation) > 0):
                problems.append("T_base_camera's rotation is not a rotation (orthonormal, determinant 1)")
            if not np.allclose(pose[3], [0, 0, 0, 1]):
                problems.append("T_base_camera's last row must be [0, 0, 0, 1]")
        distortion = np.asarray(self.distortion, np.float64).reshape(-1)
        if distortion.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(distortion)):
            problems.append(f"distortion must hold 0, 4, 5, 8, 12 or 14 finite OpenCV coefficients: {distortion.size}")
        if self.board_up is not None:
            up = np.asarray(self.board_up, np.float64)
            if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.linalg.norm(up) > 0:
                problems.append("board_up must be a nonzero direction [x, y, z] in the base frame")
        if problems:
            raise UserError("; ".join(problems))
        object.__setattr__(self, "intrinsics", k)
        object.__setattr__(self, "T_base_camera", pose)
        object.__setattr__(self, "distortion", distortion)

    @classmethod
    def load(cls, path: str | Path) -> CameraCalibration:
        """Read and check a calibration file; a UserError names the file and what is wrong."""
        data = read_json(path, "camera calibration")
        if not isinstance(data, dict):
            raise UserError(f"{path}: a camera calibration is a JSON object, not {type(data).__name__}")
        known = {"camera", "width", "height", "intrinsics", "distortion", "T_base_camera", "board_up"}
        missing = {"width", "height", "intrinsics", "T_base_camera"} - set(data)
        unknown = set(data) - known
        if missing or unknown:
            what = [f"missing {sorted(missing)}"] if missing else []
            what += [f"unknown {sorted(unknown)} (known: {sorted(known)})"] if unknown else []
            raise UserError(f"{path}: {'; '.join(what)}")
        try:
            return cls(
                width=data["width"],
                height=data["height"],
                intrinsics=np.array(data["intrinsics"], dtype=np.float64),
                T_base_camera=np.array(data["T_base_camera"], dtype=np.float64),
                distortion=np.array(data.get("distortion", []), dtype=np.float64),
                board_up=None if data.get("board_up") is None else np.array(data["board_up"], dtype=np.float64),
                camera=str(data.get("camera", "scene")),
            )
        except (ValueError, TypeError) as err:  # ragged or non-numeric lists, and the checks above
            raise UserError(f"{path}: {err}") from None

    def save(self, path: str | Path) -> Path:
        data = {
            "camera": self.camera,
            "width": self.width,
            "height": self.height,
            "intrinsics": self.intrinsics.tolist(),
            "distortion": self.distortion.tolist(),
            "T_base_camera": self.T_base_camera.tolist(),
        }
        if self.board_up is not None:
            data["board_up"] = np.asarray(self.board_up).tolist()
        write_json_atomic(path, data)
        return Path(path)

    def canvas_in_base(self, photo: np.ndarray) -> np.ndarray:
        """T_base_canvas from a photo taken by this camera (undistorted first);
        :class:`~bpp.drawing.marked_canvas.CanvasNotFound` when the markers do not give a trustworthy pose."""
        photo = np.asarray(photo)
        if photo.shape[:2] != (self.height, self.width):
            raise UserError(
                f"the photo is {photo.shape[1]}x{photo.shape[0]} px; the calibration is for {self.width}x{self.height}"
            )
        if self.distortion.size and np.any(self.distortion):
            # OpenCV: the iphumi extra
            import cv2

            photo = cv2.undistort(photo, self.intrinsics, self.distortion)
        up = None if self.board_up is None else self.T_base_camera[:3, :3].T @ self.board_up
        return canvas_in_base(self.T_base_camera, canvas_pose(photo, self.intrinsics, up=up))


@dataclass(frozen=True)
class CalibrationCheck:
    """How far each touched marker centre is from where the photo and the calibration put it."""

    errors_mm: np.ndarray
    tolerance_mm: float = TOLERANCE_MM

    @property
    def passed(self) -> bool:
        return bool(np.all(self.errors_mm <= self.tolerance_mm))

    def report(self) -> str:
        lines = [f"{name}: {error:.1f} mm" for name, error in zip(MARKER_NAMES, self.errors_mm, strict=True)]
        verdict = "passed" if self.passed else "FAILED: recalibrate (the intrinsics, then the hand-eye extrinsic)"
        return "\n".join([*lines, f"check {verdict} (tolerance {self.tolerance_mm:g} mm)"])


def check_calibration(
    calibration: CameraCalibration, photo: np.ndarray, touched: np.ndarray, tolerance_mm: float = TOLERANCE_MM
) -> CalibrationCheck:
    """Compare the canvas pose from `photo` with `touched`, the (4, 3) base-frame positions of the four markers'
    centres (top-left, top-right, bottom-right, bottom-left of the canvas upright) touched with the pen tip."""
    touched = np.asarray(touched, dtype=np.float64)
    if touched.shape != (4, 3) or not np.all(np.isfinite(touched)):
        raise UserError(f"touched points must be 4 finite [x, y, z] positions in metres, got shape {touched.shape}")
    canvas = calibration.canvas_in_base(photo)
    markers = canvas[:3, :3] @ CanvasLayout().marker_points().T + canvas[:3, 3:4]
    return CalibrationCheck(np.linalg.norm(markers.T - touched, axis=1) * 1000.0, tolerance_mm)


def read_touched(path: str | Path) -> np.ndarray:
    """The touched marker centres from a JSON file: ``{"touched": [[x, y, z] x 4]}`` (metres, base frame)."""
    data = read_json(path, "touched marker positions")
    if not isinstance(data, dict) or "touched" not in data:
        raise UserError(f'{path}: expected {{"touched": [[x, y, z], ...4 points]}} in metres, base frame')
    try:
        touched = np.array(data["touched"], dtype=np.float64)
    except (ValueError, TypeError) as err:
        raise UserError(f"{path}: touched: {err}") from None
    if touched.shape != (4, 3) or not np.all(np.isfinite(touched)):
        raise UserError(f"{path}: touched must be 4 finite [x, y, z] positions in metres, got shape {touched.shape}")
    return touched


def simulated_lab(folder: str | Path, seed: int = 0, touch_noise_mm: float = 0.5) -> dict[str, Path]:
    """The simulator standing in for a lab: write the scene camera's calibration, a photo of a canvas at a random
    placement (the arm swung aside) and the markers' centres as a pen would touch them (with `touch_noise_mm` of
    noise) into `folder`. Returns the three paths."""
    # imageio: for video and GIF files only
    import imageio.v3 as iio

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    placement = random_placement(rng)
    truth = canvas_transform(placement["u"], placement["v"], placement["angle"])
    scene = Scene(image_size=32)
    try:
        scene.reset(truth, ASIDE)
        calibration = CameraCalibration(
            width=PHOTO_SIZE,
            height=PHOTO_SIZE,
            intrinsics=scene.camera_intrinsics("scene", PHOTO_SIZE),
            T_base_camera=scene.camera_pose("scene"),
            board_up=BOARD[:, 1],
        )
        photo = scene.render("scene", PHOTO_SIZE)
    finally:
        scene.close()
    markers = (truth[:3, :3] @ CanvasLayout().marker_points().T + truth[:3, 3:4]).T
    touched = markers + rng.normal(0.0, touch_noise_mm / 1000.0, markers.shape)
    paths = {name: folder / f"{name}{suffix}" for name, suffix in
             (("calibration", ".json"), ("photo", ".png"), ("touched", ".json"))}  # fmt: skip
    calibration.save(paths["calibration"])
    iio.imwrite(paths["photo"], photo)
    write_json_atomic(paths["touched"], {"touched": touched.tolist()})
    return paths
