"""Where a drawing demonstration's canvas lies, measured by the phone that made it (``bpp iphumi process --canvas``).

A drawing made with iPhUMI on DrawAnything-Real's marked canvas (:mod:`bpp.drawing.marked_canvas`) starts with the
phone held still above the canvas, so that its main camera sees the four red markers: their photo gives the canvas
pose in the camera's frame, ARKit's pose of that frame gives it in the phone's world frame, and every pose of the
demonstration can then be written in the canvas's frame, the frame the arm's demonstrations and observations use.
"""

from __future__ import annotations

import numpy as np

from bpp.benchmarks.iphumi.recording import Recording, RecordingError
from bpp.benchmarks.iphumi.video import read_frames
from bpp.core.poses import interpolate_poses
from bpp.drawing.marked_canvas import CanvasNotFound, canvas_pose

LOOK_SECONDS = 1.0
"""How long after a segment's start the main camera's frames are searched for the canvas."""
TRIES = 6
"""How many of those frames, evenly spaced, are tried; the first that gives a pose is used."""
OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""ARKit's camera axes (x right, y up, z back) -> OpenCV's (x right, y down, z forward)."""


def canvas_in_world(recording: Recording, start: float) -> np.ndarray:
    """(4, 4) T_world_canvas: the canvas pose in the phone's world frame, from the first of the main camera's frames in
    the `LOOK_SECONDS` after epoch time `start` that shows its four markers (:class:`RecordingError` if none does)."""
    times = recording.rgb_times
    window = np.flatnonzero((times >= start) & (times <= start + LOOK_SECONDS))
    if not len(window):
        raise RecordingError(f"{recording.name}: no main-camera frame in the {LOOK_SECONDS:g} s after a segment starts")
    chosen = window[np.unique(np.linspace(0, len(window) - 1, min(TRIES, len(window))).round().astype(int))]
    frames, _ = read_frames(recording.rgb_path, chosen, len(times))
    seen = []
    for index, frame in zip(chosen, frames, strict=True):
        try:
            found = canvas_pose(frame, recording.main_intrinsics)
        except CanvasNotFound as err:
            seen.append(err.reason)
            continue
        camera = interpolate_poses(recording.pose_times, recording.poses, times[index : index + 1])[0]
        return camera @ OPENCV @ found
    raise RecordingError(
        f"{recording.name}: none of {len(chosen)} main-camera frames in the {LOOK_SECONDS:g} s after a segment starts "
        f"shows the canvas's four red markers ({', '.join(sorted(set(seen)))}); hold the phone still above the canvas "
        "at the start of each drawing"
    )
