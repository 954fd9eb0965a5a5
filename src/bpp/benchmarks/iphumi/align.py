"""From a demonstration's recordings to aligned tool-centre-point trajectories on one 60 Hz grid, checked.

* **The tool-centre point (TCP).** ARKit tracks the phone's main camera; the gripper's fingertip centre sits at a
  fixed transform from it, given by the phone mount (:data:`MOUNTS`, or a file for other phones):
  ``T_world_tcp = T_world_camera @ T_camera_tcp``.
* **One grid.** Every phone of a demonstration logs wall-clock times and, in a shared ARKit session, poses in one
  world frame. The grid runs at 60 Hz over the time all phones overlap; poses are interpolated there with positions
  linear and rotations by slerp, on the rotation group; each camera contributes its latest frame at or before a
  grid time; gripper widths (measured at the ultrawide camera's ~10 Hz) are interpolated linearly.
* **Checks** (:func:`check_demonstration`) reject a demonstration with its reasons: a TCP faster than a hand moves
  (tracking lost), grippers too far apart or on the wrong sides, a head phone too far away.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bpp.benchmarks.iphumi.recording import Demonstration, Recording, RecordingError
from bpp.core.poses import interpolate_poses, invert, make_pose, rotation_angle
from bpp.utils import read_json

GRID_HZ = 60.0
"""The phones' frame rate and the alignment grid's."""


def _mount(tilt_deg: float, translation) -> np.ndarray:
    angle = np.deg2rad(tilt_deg)
    tilt = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    return make_pose(tilt @ np.diag([1.0, -1.0, -1.0]), translation)


MOUNTS: dict[str, np.ndarray] = {
    # iPhone 15 Pro in the iPhUMI gripper mount: a 15-degree tilt about the camera's x axis composed with a flip
    # to the gripper's axes (x right, y down, z forward); the fingertips 6.4 cm below and 21.1 cm in front of the lens
    "iPhone16,1": _mount(15.0, (0.0, -0.06441, -0.211397)),
}
"""``T_camera_tcp`` of known phones in the iPhUMI gripper mount, by ARKit's device identifier."""
HEAD_MOUNT = _mount(0.0, (0.0, 0.0, 0.0))
"""A head-mounted phone is a camera: its "TCP" is the camera with the gripper's axis convention."""


def load_mounts(path: str | Path | None) -> dict[str, np.ndarray]:
    """The built-in mounts, plus (or overridden by) those in a JSON file ``{device identifier: {"rotation": 3x3
    row-major, "translation": [x, y, z] metres}}`` giving ``T_camera_tcp`` for other phones or mounts."""
    mounts = dict(MOUNTS)
    if path is None:
        return mounts
    data = read_json(path, "phone mount calibration")
    if not isinstance(data, dict) or not data:
        raise RecordingError(f"{path}: must map device identifiers to {{'rotation': 3x3, 'translation': [x, y, z]}}")
    for device, entry in data.items():
        try:
            rotation = np.asarray(entry["rotation"], dtype=np.float64)
            translation = np.asarray(entry["translation"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise RecordingError(f"{path}: {device!r} needs 'rotation' (3x3) and 'translation' (3 numbers)") from None
        if rotation.shape != (3, 3) or translation.shape != (3,) or not np.all(np.isfinite(rotation)):
            raise RecordingError(f"{path}: {device!r}: rotation must be 3x3 and translation 3 numbers")
        if np.abs(rotation @ rotation.T - np.eye(3)).max() > 1e-4 or np.linalg.det(rotation) < 0:
            raise RecordingError(f"{path}: {device!r}: the rotation is not a proper rotation matrix")
        mounts[str(device)] = make_pose(rotation, translation)
    return mounts


def camera_to_tcp(recording: Recording, mounts: Mapping[str, np.ndarray]) -> np.ndarray:
    """``T_camera_tcp`` (4, 4) of the phone that made `recording`."""
    if recording.side == "head":
        return HEAD_MOUNT
    if recording.device not in mounts:
        known = ", ".join(sorted(mounts))
        raise RecordingError(
            f"{recording.name}: no mount calibration for the phone {recording.device or '(none named)'!r} (known: "
            f"{known}); give one with --mounts FILE"
        )
    return mounts[recording.device]


@dataclass
class Aligned:
    """A demonstration on its 60 Hz grid. Per phone side: TCP poses (N, 4, 4) in the shared world frame, the
    latest main-camera, ultrawide and depth frame indices at or before each grid time (N,), gripper width (N,)."""

    demonstration: Demonstration
    times: np.ndarray
    """(N,) epoch seconds."""
    tcp: dict[str, np.ndarray] = field(default_factory=dict)
    camera: dict[str, np.ndarray] = field(default_factory=dict)
    """Side -> the phone camera's poses (N, 4, 4), for the checks."""
    rgb_index: dict[str, np.ndarray] = field(default_factory=dict)
    ultrawide_index: dict[str, np.ndarray] = field(default_factory=dict)
    depth_index: dict[str, np.ndarray] = field(default_factory=dict)
    width: dict[str, np.ndarray] = field(default_factory=dict)


def latest_index(times: np.ndarray, at: np.ndarray) -> np.ndarray:
    """For each time in `at`, the index of the latest of `times` (increasing) at or before it (the first if none)."""
    return np.clip(np.searchsorted(times, at, side="right") - 1, 0, max(len(times) - 1, 0))


def align(
    demonstration: Demonstration,
    widths: Mapping[str, tuple[np.ndarray, np.ndarray]],
    mounts: Mapping[str, np.ndarray],
) -> Aligned:
    """Align a demonstration's phones on one 60 Hz grid. `widths` maps each gripper side to (times (K,), widths
    (K,)) measured from its ultrawide video."""
    phones = demonstration.phones
    start = max(r.pose_times[0] for r in phones.values())
    stop = min(r.pose_times[-1] for r in phones.values())
    if stop - start < 2.0 / GRID_HZ:
        raise RecordingError(
            f"{demonstration.group}: the phones' recordings overlap for {max(stop - start, 0) * 1e3:.0f} ms; they "
            "must overlap in time (same demonstration, clocks in sync)"
        )
    times = start + np.arange(int(np.floor((stop - start) * GRID_HZ + 1e-9)) + 1) / GRID_HZ
    out = Aligned(demonstration, times)
    for side, recording in phones.items():
        camera = interpolate_poses(recording.pose_times, recording.poses, times)
        out.camera[side] = camera
        out.tcp[side] = camera @ camera_to_tcp(recording, mounts)
        out.rgb_index[side] = latest_index(recording.rgb_times, times)
        present = np.flatnonzero(~np.isnan(recording.ultrawide_times))
        out.ultrawide_index[side] = latest_index(recording.ultrawide_times[present], times)
        if len(recording.depth_times):
            out.depth_index[side] = latest_index(recording.depth_times, times)
        if side in widths:
            width_times, values = widths[side]
            out.width[side] = np.interp(times, width_times, values)
    return out


@dataclass(frozen=True)
class Limits:
    """What a plausible demonstration stays within (the checks of :func:`check_demonstration`)."""

    max_speed: float = 3.0
    """TCP speed limit (m/s); faster means tracking jumped."""
    max_gripper_distance: float = 1.5
    """Most distance between the two grippers at the start (m)."""
    max_gripper_offset: tuple[float, float, float] = (1.0, 0.5, 0.5)
    """Most |x|, |y|, |z| of the right phone seen from the left phone's camera at the start (m)."""
    max_relative_rotation_deg: float = 150.0
    """Most rotation between the two phones at the start."""
    max_head_distance: float = 2.0
    """Most distance from a gripper phone to the head phone at the start (m)."""


def check_demonstration(aligned: Aligned, limits: Limits = Limits()) -> list[str]:
    """Every reason the aligned demonstration is implausible ([] if none)."""
    reasons = []
    dt = np.diff(aligned.times)
    for side, tcp in aligned.tcp.items():
        if side == "head" or len(dt) == 0:
            continue
        speed = np.linalg.norm(np.diff(tcp[:, :3, 3], axis=0), axis=1) / dt
        fastest = int(np.argmax(speed))
        if speed[fastest] > limits.max_speed:
            at = aligned.times[fastest] - aligned.times[0]
            reasons.append(
                f"the {side} gripper moves at {speed[fastest]:.1f} m/s at {at:.2f} s (limit {limits.max_speed:g} "
                "m/s): tracking jumped"
            )
    camera = aligned.camera
    if "left" in camera and "right" in camera:
        left, right = camera["left"][0], camera["right"][0]
        distance = float(np.linalg.norm(right[:3, 3] - left[:3, 3]))
        if distance > limits.max_gripper_distance:
            reasons.append(f"the grippers start {distance:.2f} m apart (limit {limits.max_gripper_distance:g} m)")
        offset = (invert(left) @ right)[:3, 3]
        if np.any(np.abs(offset) > limits.max_gripper_offset):
            reasons.append(
                f"the right phone starts at {np.round(offset, 2).tolist()} m from the left one (limits "
                f"{list(limits.max_gripper_offset)})"
            )
        if offset[0] < 0:
            reasons.append("the right phone starts to the left of the left phone: sides flipped")
        angle = float(np.rad2deg(rotation_angle(left[:3, :3], right[:3, :3])))
        if angle > limits.max_relative_rotation_deg:
            reasons.append(f"the phones start {angle:.0f} degrees apart (limit {limits.max_relative_rotation_deg:g})")
    if "head" in camera:
        for side in ("left", "right"):
            if side in camera:
                distance = float(np.linalg.norm(camera[side][0, :3, 3] - camera["head"][0, :3, 3]))
                if distance > limits.max_head_distance:
                    reasons.append(
                        f"the {side} gripper starts {distance:.2f} m from the head phone (limit "
                        f"{limits.max_head_distance:g} m)"
                    )
    return reasons
