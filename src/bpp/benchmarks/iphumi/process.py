"""Demonstrations recorded with iPhUMI -> episodes of a bpp store (``bpp iphumi process``), and one recording ->
one behavior prompt (``bpp iphumi prompt``).

Per demonstration (its phones' recordings): the gripper's calibration recording gives the finger tags' width range
(:mod:`bpp.benchmarks.iphumi.gripper`); the ultrawide video gives the width over time; the phones are aligned on one
60 Hz grid (:mod:`bpp.benchmarks.iphumi.align`) and checked; the task labels cut it into segments, one episode per
segment (a demonstration without labels is one episode of the task named by its session); each episode is sampled
at the policy rate. Per step, with arm 0 the right gripper (or the only one) and arm 1 the left one of a bimanual
demonstration:

* ``pose`` (9,): arm 0's TCP pose in the frame of its own pose at the episode's start (position in metres, then the
  6-D rotation), since a phone's world frame is arbitrary per recording; ``arm1_pose`` the same for arm 1, in the
  same frame (so the arms' relation is kept);
* ``width`` (1,) and ``arm1_width``: the gripper opening in metres, 0 when closed;
* ``rgb`` / ``arm1_rgb`` / ``head_rgb``: the main cameras, letterboxed to a square and resized; optionally
  ``ultrawide`` / ``arm1_ultrawide`` and ``depth`` / ``arm1_depth`` ((S, S, 1) float16 metres, 0 outside the image);
* ``action`` (10 per arm): the step to the next pose in the current pose's frame (position + 6-D rotation,
  :func:`bpp.core.poses.relative_actions`) and the next step's width;
* with ``canvas`` (drawings on DrawAnything-Real's marked canvas, single arm): ``canvas_pose`` (9,), the canvas
  measured from the main camera at the episode's start (:mod:`bpp.benchmarks.iphumi.canvas`), in the frame of
  ``pose``, and ``tip_in_canvas`` (9,), the TCP (the pen's tip, for a drawing gripper's mount) in the canvas's frame.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from bpp.benchmarks.iphumi import gripper
from bpp.benchmarks.iphumi.align import GRID_HZ, Aligned, Limits, align, check_demonstration, load_mounts
from bpp.benchmarks.iphumi.canvas import canvas_in_world
from bpp.benchmarks.iphumi.recording import (
    Demonstration,
    Recording,
    RecordingError,
    TaskLabel,
    read_recording,
)
from bpp.benchmarks.iphumi.video import read_frames
from bpp.core.poses import invert, pose_to_vector, relative_actions
from bpp.errors import UserError
from bpp.utils import check_fields, write_json_atomic

CAMERAS = ("rgb", "ultrawide", "depth")
ARM_PREFIX = ("", "arm1_")
"""Key prefixes of arm 0 (the right gripper, or the only one) and arm 1 (the left gripper of a bimanual demo)."""


@dataclass(frozen=True)
class ProcessSettings:
    """How recordings become episodes (the flags of ``bpp iphumi process`` besides the folders)."""

    fps: float = 10.0
    """The policy rate episodes are sampled at (a divisor of the phones' 60 Hz)."""
    image_size: int = 96
    """Side of the square camera frames stored (px); frames are letterboxed (black borders), not stretched."""
    cameras: tuple[str, ...] = ("rgb",)
    """Which of each phone's streams to store: rgb (main camera), ultrawide, depth (LiDAR, if recorded)."""
    mounts: Path | None = None
    """A JSON file of phone mount calibrations for phones other than the built-in ones (see docs/iphumi.md)."""
    min_steps: int = 4
    """Segments shorter than this many policy steps are left out (with the reason)."""
    include_error_correction: bool = True
    """Keep demonstrations the app marked as error corrections."""
    canvas: bool = False
    """Drawings on the marked canvas (single arm): measure it as each episode starts, store the pen in its frame."""
    limits: Limits = Limits()

    def __post_init__(self):
        check_fields(
            self,
            (
                "fps",
                0 < self.fps <= GRID_HZ and abs(GRID_HZ / self.fps - round(GRID_HZ / self.fps)) < 1e-9,
                "a divisor of 60 (e.g. 10, 15, 20, 30, 60)",
            ),
            ("image_size", 8 <= self.image_size <= 512, "in [8, 512] px"),
            ("cameras", set(self.cameras) <= set(CAMERAS), f"some of {', '.join(CAMERAS)}"),
            ("min_steps", self.min_steps >= 2, ">= 2"),
            ("limits.max_speed", self.limits.max_speed > 0, "> 0 m/s"),
            ("limits.max_gripper_distance", self.limits.max_gripper_distance > 0, "> 0 m"),
            (
                "limits.max_gripper_offset",
                len(self.limits.max_gripper_offset) == 3 and all(v > 0 for v in self.limits.max_gripper_offset),
                "three distances > 0 m",
            ),
            (
                "limits.max_relative_rotation_deg",
                0 < self.limits.max_relative_rotation_deg <= 180,
                "in (0, 180] degrees",
            ),
            ("limits.max_head_distance", self.limits.max_head_distance > 0, "> 0 m"),
        )

    @property
    def stride(self) -> int:
        return round(GRID_HZ / self.fps)

    def digest(self) -> str:
        """What identifies the settings' output, for resuming (the mount file by content)."""
        data = asdict(self)
        data["mounts"] = Path(self.mounts).read_text() if self.mounts else None
        return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------ the gripper
def gripper_tags(demonstration: Demonstration, side: str) -> str:
    """Which tag pair a gripper carries: a single gripper has the right one's ids (0, 1) whichever phone holds it."""
    return side if len(demonstration.grippers) > 1 else "right"


def ultrawide_frames(recording: Recording) -> tuple[np.ndarray, np.ndarray]:
    """(the ultrawide frames (K, H, W, 3) uint8, their times (K,)): the video holds one frame per non-empty entry of
    ``ultrawideRGBTimes``."""
    times = recording.ultrawide_times[~np.isnan(recording.ultrawide_times)]
    frames, _ = read_frames(recording.ultrawide_path, np.arange(len(times)), len(times))
    return frames, times


def calibration_for(recording: Recording, tags: str, export_index: Mapping[str, Path], cache: dict):
    """The gripper calibration a demonstration recording names, computed from its calibration recording (cached)."""
    name = recording.calibration_name
    if not name:
        raise RecordingError(f"{recording.name}: names no gripper calibration run (gripperCalibrationRunName)")
    if name not in export_index:
        raise RecordingError(
            f"{recording.name}: its gripper calibration run {name!r} is not among the recordings (export the "
            "calibration recording with the demonstrations)"
        )
    folder = Path(export_index[name])
    key = hash_files(calibration_files(folder), tags)[:32]  # a missing video is named by read_recording below
    if key in cache:
        return cache[key]
    saved = calibration_cache() / f"{key}.json"
    if saved.is_file():
        try:
            cache[key] = gripper.GripperCalibration.from_json(json.loads(saved.read_text()))
            return cache[key]
        except (OSError, ValueError):
            pass  # an unreadable or outdated cache entry: computed again below
    calibration = read_recording(folder)
    if calibration.kind != "grippercalibration":
        raise RecordingError(f"{recording.name}: {name!r}, named as its calibration run, is a {calibration.kind}")
    frames, _ = ultrawide_frames(calibration)
    try:
        cache[key] = gripper.calibrate(frames, calibration.ultrawide_intrinsics, tags)
    except UserError as err:
        raise RecordingError(f"gripper calibration {name}: {err}") from None
    try:
        saved.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(saved, cache[key].to_json())
    except OSError:
        pass  # a cache that cannot be written costs only time
    return cache[key]


def calibration_files(folder: Path) -> tuple[Path, Path]:
    """What a gripper calibration is measured from: its recording's JSON and ultrawide video."""
    return folder / f"{folder.name}.json", folder / f"{folder.name}_ultrawidergb.mp4"


def hash_files(paths: Iterable[Path], seed: str = "") -> str:
    """SHA-256 (hex) of `seed` and of each file's name, size and content, read in chunks; a missing file counts as
    missing (it is refused where it is read)."""
    digest = hashlib.sha256(seed.encode())
    for path in map(Path, paths):
        size = path.stat().st_size if path.is_file() else -1
        digest.update(f"\0{path.name}\0{size}\0".encode())
        if size >= 0:
            with open(path, "rb") as f:
                while chunk := f.read(1 << 20):
                    digest.update(chunk)
    return digest.hexdigest()


def calibration_cache() -> Path:
    """Where gripper calibrations are kept once computed, by the content of their recording (so a prompt or a new
    export does not measure a calibration recording again): ``$BPP_CACHE/iphumi`` (default ``~/.cache/bpp``)."""
    root = os.environ.get("BPP_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bpp"
    return Path(root) / "iphumi"


def measure_widths(demonstration: Demonstration, export_index: Mapping[str, Path], cache: dict) -> dict:
    """Side -> (times (K,), widths (K,) metres, 0 closed) of each gripper, from its ultrawide video."""
    widths = {}
    for side in demonstration.grippers:
        recording = demonstration.phones[side]
        tags = gripper_tags(demonstration, side)
        calibration = calibration_for(recording, tags, export_index, cache)
        frames, times = ultrawide_frames(recording)
        try:
            widths[side] = (times, gripper.width_series(frames, recording.ultrawide_intrinsics, tags, calibration))
        except UserError as err:
            raise RecordingError(f"{recording.name}: {err}") from None
    return widths


def layout(demonstration: Demonstration, settings: ProcessSettings) -> str:
    """What its episodes hold, in words: one gripper or two, and a head camera or not (episodes of different layouts
    have different keys, so they cannot share a store)."""
    arms = "bimanual" if len(demonstration.grippers) > 1 else "single-arm"
    return f"{arms} with a head camera" if "head" in demonstration.phones and "rgb" in settings.cameras else arms


# ------------------------------------------------------------------------------------------------ segments
def labels_of(demonstration: Demonstration) -> tuple[TaskLabel, ...]:
    """The demonstration's task labels: those of its voice host if exactly one phone is, else of the head, left,
    right phone, the first that has labels."""
    phones = demonstration.phones
    hosts = [r for r in phones.values() if r.meta.get("isVoiceHost")]
    if len(hosts) == 1 and hosts[0].labels:
        return hosts[0].labels
    for side in ("head", "left", "right"):
        if side in phones and phones[side].labels:
            return phones[side].labels
    return ()


def segments(aligned: Aligned, settings: ProcessSettings) -> list[tuple[str, np.ndarray]]:
    """[(task name, grid indices at the policy rate)] of the labelled segments (or the whole demonstration, named by
    its session, if it has no labels)."""
    demonstration = aligned.demonstration
    first = next(iter(demonstration.phones.values()))
    labels = labels_of(demonstration) or (TaskLabel(first.session, aligned.times[0], aligned.times[-1] + 1e-9),)
    out = []
    for label in labels:
        start, stop = np.searchsorted(aligned.times, [label.start, label.end], side="left")
        out.append((label.name, np.arange(start, stop, settings.stride)))
    return out


# ------------------------------------------------------------------------------------------------ episodes
def letterbox(frames: np.ndarray, size: int, fill=0) -> np.ndarray:
    """(N, h, w, C) frames scaled to fit inside size x size -> (N, size, size, C), centred, `fill` around."""
    n, h, w, c = frames.shape
    out = np.full((n, size, size, c), fill, dtype=frames.dtype)
    top, left = (size - h) // 2, (size - w) // 2
    out[:, top : top + h, left : left + w] = frames
    return out


def fitted_size(width: int, height: int, size: int) -> tuple[int, int]:
    """(w, h) of a width x height frame scaled to fit in a size x size square (even sides are not required)."""
    scale = size / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def _camera_frames(recording: Recording, camera: str, indices: np.ndarray, size: int) -> np.ndarray:
    if camera == "depth":
        depth = recording.depth_frames()[indices].astype(np.float32)

        h, w = depth.shape[1:]
        fw, fh = fitted_size(w, h, size)
        scaled = np.stack([np.asarray(Image.fromarray(d).resize((fw, fh), Image.NEAREST)) for d in depth])
        return letterbox(scaled[..., None], size).astype(np.float16)
    if camera == "rgb":
        path, logged = recording.rgb_path, len(recording.rgb_times)
    else:
        path, logged = recording.ultrawide_path, int(np.sum(~np.isnan(recording.ultrawide_times)))
    frames, _ = read_frames(path, indices, logged, fit=size)
    return letterbox(frames, size)


def episodes_of(
    demonstration: Demonstration,
    export_index: Mapping[str, Path],
    settings: ProcessSettings,
    calibrations: dict | None = None,
    mounts: Mapping[str, np.ndarray] | None = None,
    whole: bool = False,
) -> tuple[list[dict], list[str]]:
    """A demonstration -> ([episode: {"task": name, "steps": {key: (L, ...)}, "start": seconds}], [reasons segments
    were left out]). Raises RecordingError with the reasons if the demonstration as a whole is unusable. With
    `whole`, the whole demonstration is one episode whatever its labels (a behavior prompt)."""
    mounts = load_mounts(settings.mounts) if mounts is None else mounts
    widths = measure_widths(demonstration, export_index, {} if calibrations is None else calibrations)
    aligned = align(demonstration, widths, mounts)
    reasons = check_demonstration(aligned, settings.limits)
    if reasons:
        raise RecordingError(f"{demonstration.group}: " + "; ".join(reasons))
    if whole:
        first = next(iter(demonstration.phones.values()))
        labels = labels_of(demonstration)
        task = labels[0].name if len(labels) == 1 else first.session
        parts = [(task, np.arange(0, len(aligned.times), settings.stride))]
    else:
        parts = segments(aligned, settings)
    episodes, skipped = [], []
    arms = demonstration.grippers
    for task, rows in parts:
        if len(rows) < settings.min_steps:
            skipped.append(f"{demonstration.group}: segment {task!r} has {len(rows)} steps (< {settings.min_steps})")
            continue
        reference = invert(aligned.tcp[arms[0]][rows[0]])
        steps: dict[str, np.ndarray] = {}
        actions = []
        for prefix, side in zip(ARM_PREFIX, arms, strict=False):
            tcp = aligned.tcp[side][rows]
            steps[f"{prefix}pose"] = pose_to_vector(reference @ tcp).astype(np.float32)
            width = aligned.width[side][rows]
            steps[f"{prefix}width"] = width[:, None].astype(np.float32)
            next_width = np.concatenate([width[1:], width[-1:]])
            actions.append(np.concatenate([relative_actions(tcp), next_width[:, None]], axis=1))
            recording = demonstration.phones[side]
            for camera in settings.cameras:
                index = {"rgb": aligned.rgb_index, "ultrawide": aligned.ultrawide_index, "depth": aligned.depth_index}
                if camera == "depth" and not recording.has_depth:
                    raise RecordingError(f"{recording.name}: --cameras asks for depth, which it did not record")
                rows_of = index[camera][side][rows]
                steps[f"{prefix}{camera}"] = _camera_frames(recording, camera, rows_of, settings.image_size)
        if "head" in demonstration.phones and "rgb" in settings.cameras:
            steps["head_rgb"] = _camera_frames(
                demonstration.phones["head"], "rgb", aligned.rgb_index["head"][rows], settings.image_size
            )
        steps["action"] = np.concatenate(actions, axis=1).astype(np.float32)
        if settings.canvas:
            if len(arms) > 1:
                raise RecordingError(f"{demonstration.group}: --canvas is for single-arm drawing demonstrations")
            canvas = canvas_in_world(demonstration.phones[arms[0]], float(aligned.times[rows[0]]))
            steps["canvas_pose"] = np.repeat(pose_to_vector(reference @ canvas)[None], len(rows), 0).astype(np.float32)
            steps["tip_in_canvas"] = pose_to_vector(invert(canvas) @ aligned.tcp[arms[0]][rows]).astype(np.float32)
        episodes.append({"task": task, "steps": steps, "start": float(aligned.times[rows[0]] - aligned.times[0])})
    if not episodes:
        raise RecordingError(f"{demonstration.group}: no segment long enough ({'; '.join(skipped)})")
    return episodes, skipped
