"""iPhUMI recordings as the phone app exports them: one folder per phone and recording, read and validated.

A recording folder is named ``<start>_<number>_<session>_<type>_<side>``: the start time in ISO-8601 UTC with ':'
written as '-', a five-digit number, the data-collection session's name, ``demonstration`` or
``grippercalibration``, and the phone's place (``left``, ``right`` or ``head``). It holds ``<name>.json`` (times,
ARKit poses, intrinsics, task labels; :class:`Recording`), the main camera's ``<name>_rgb.mp4``, the ultrawide
camera's ``<name>_ultrawidergb.mp4`` and optionally LiDAR depth, ``<name>_depth.raw`` (headerless 192x256 float16
frames, metres). Phones of one bimanual demonstration share the name up to the side and list each other in
``sidesPresent``.

Everything a user's file can get wrong is a :class:`RecordingError` naming the recording and the problem.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from bpp.errors import UserError
from bpp.utils import read_json

SIDES = ("right", "left", "head")
"""Where a phone is: on the right or the left gripper (a single gripper is either), or on the head (a camera only)."""
KINDS = ("demonstration", "grippercalibration")
DEPTH_SHAPE = (192, 256)
"""(height, width) of a LiDAR depth frame."""
NAME = re.compile(
    r"^(?P<start>\d{4}-\d{2}-\d{2}T[\d\-.]+Z?)_(?P<number>\d{5})_(?P<session>.+)_(?P<kind>demonstration|"
    r"grippercalibration)_(?P<side>left|right|head)$"
)
EXPECTED_NAME = "expected <start>_<5 digits>_<session>_<demonstration|grippercalibration>_<left|right|head>"
_TIME_LISTS = ("poseTimes", "rgbTimes", "ultrawideRGBTimes", "depthTimes")


class RecordingError(UserError):
    """A recording (or a group of them) that cannot be used, and why."""


def parse_time(text: str) -> float:
    """An ISO-8601 time (``2025-03-01T12:30:45.123Z``, or with an explicit offset) -> seconds since the Unix epoch.
    A time without a zone is taken as UTC, as the app writes it."""
    if not isinstance(text, str) or not text:
        raise ValueError(f"not a time string: {text!r}")
    value = datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
    if value.tzinfo is None:
        value = value.replace(tzinfo=timezone.utc)
    return value.timestamp()


def parse_times(values, what: str, where: str, allow_missing: bool = False) -> np.ndarray:
    """A list of ISO-8601 strings -> (N,) float64 seconds, strictly increasing; "" -> NaN where `allow_missing`."""
    if not isinstance(values, list):
        raise RecordingError(f"{where}: {what!r} must be a list of time strings, got {type(values).__name__}")
    out = np.full(len(values), np.nan)
    for i, text in enumerate(values):
        if allow_missing and text == "":
            continue
        try:
            out[i] = parse_time(text)
        except (ValueError, TypeError):
            raise RecordingError(f"{where}: {what}[{i}] = {text!r} is not an ISO-8601 time") from None
    present = out[~np.isnan(out)]
    bad = np.flatnonzero(np.diff(present) <= 0)
    if len(bad):  # a frame logged twice, or a clock that went back
        raise RecordingError(
            f"{where}: {what} is not strictly increasing ({len(bad)} time(s) go back or repeat, the first after "
            f"{len(np.flatnonzero(~np.isnan(out[: bad[0] + 1])))} entries)"
        )
    return out


@dataclass(frozen=True)
class TaskLabel:
    """One labelled segment of a demonstration: a task name and its [start, end] times (epoch seconds)."""

    name: str
    start: float
    end: float


@dataclass
class Recording:
    """One phone's recording: its folder, what its name says, and its JSON parsed and checked.

    Times are float64 seconds since the Unix epoch. ``ultrawide_times`` is NaN where the 60 Hz list has no new
    ultrawide frame (the ultrawide camera runs at about 10 Hz)."""

    folder: Path
    name: str
    start: str
    number: str
    session: str
    kind: str
    side: str
    meta: dict = field(repr=False)
    pose_times: np.ndarray = field(repr=False)
    poses: np.ndarray = field(repr=False)
    """(N, 4, 4) ARKit camera-to-world transforms, metres (camera axes: x right, y up, z toward the user)."""
    rgb_times: np.ndarray = field(repr=False)
    ultrawide_times: np.ndarray = field(repr=False)
    depth_times: np.ndarray = field(repr=False)
    main_intrinsics: np.ndarray = field(repr=False)
    ultrawide_intrinsics: np.ndarray = field(repr=False)
    labels: tuple[TaskLabel, ...] = ()

    # ------------------------------------------------------------------ files
    @property
    def json_path(self) -> Path:
        return self.folder / f"{self.name}.json"

    @property
    def rgb_path(self) -> Path:
        return self.folder / f"{self.name}_rgb.mp4"

    @property
    def ultrawide_path(self) -> Path:
        return self.folder / f"{self.name}_ultrawidergb.mp4"

    @property
    def depth_path(self) -> Path:
        return self.folder / f"{self.name}_depth.raw"

    # ----------------------------------------------------------------- fields
    @property
    def group(self) -> str:
        """What the phones of one demonstration share: the folder name without the side."""
        return self.name.rsplit("_", 1)[0]

    @property
    def sides_present(self) -> tuple[str, ...]:
        return tuple(self.meta.get("sidesPresent") or (self.side,))

    @property
    def device(self) -> str:
        return str(self.meta.get("deviceIdentifier", ""))

    @property
    def calibration_name(self) -> str:
        """The folder name of the gripper calibration recording this demonstration uses ("" if none is named)."""
        return str(self.meta.get("gripperCalibrationRunName") or "")

    @property
    def has_depth(self) -> bool:
        return bool(self.meta.get("hasDepth")) and self.depth_path.is_file()

    @property
    def is_error_correction(self) -> bool:
        return bool(self.meta.get("isErrorCorrection"))

    @property
    def duration(self) -> float:
        return float(self.pose_times[-1] - self.pose_times[0])

    def depth_frames(self) -> np.ndarray:
        """(D, 192, 256) float32 depth in metres, memory-mapped from the raw file, checked against ``depthTimes``."""
        size = self.depth_path.stat().st_size
        frame = DEPTH_SHAPE[0] * DEPTH_SHAPE[1] * 2
        if size % frame:
            raise RecordingError(
                f"{self.depth_path}: {size} bytes is not a whole number of {DEPTH_SHAPE[0]}x{DEPTH_SHAPE[1]} float16 "
                "frames (a truncated file?)"
            )
        frames = np.memmap(self.depth_path, dtype="<f2", mode="r").reshape(-1, *DEPTH_SHAPE)
        if len(frames) < len(self.depth_times):
            raise RecordingError(
                f"{self.depth_path}: {len(frames)} depth frames for {len(self.depth_times)} depth times (truncated?)"
            )
        return frames


def parse_name(folder: Path) -> dict[str, str]:
    """The parts of a recording folder's name; RecordingError if it is not an app recording's name."""
    match = NAME.match(folder.name)
    if match is None:
        raise RecordingError(f"{folder}: not an iPhUMI recording folder name ({EXPECTED_NAME})")
    return match.groupdict()


def _matrices(values, count: int, shape: tuple[int, int], what: str, where: str) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=np.float64)
    except (ValueError, TypeError):
        raise RecordingError(f"{where}: {what} must hold numbers, {shape[0]}x{shape[1]} each") from None
    size = shape[0] * shape[1]
    if count == 0 and array.size == 0:
        return np.zeros((0, *shape))
    if array.ndim == 2 and array.shape[1] == size:
        array = array.reshape(-1, *shape)
    if array.shape[1:] != shape or (count >= 0 and len(array) != count):
        expected = f"{count} x " if count >= 0 else ""
        raise RecordingError(f"{where}: {what} must be {expected}{shape[0]}x{shape[1]} (row-major), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise RecordingError(f"{where}: {what} holds non-finite numbers")
    return array


def read_recording(folder: str | Path, check_media: bool = True) -> Recording:
    """Read and check one recording folder: its name, JSON, times, poses, intrinsics and labels, and (with
    `check_media`) that its videos exist. Raises :class:`RecordingError` with the reason."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such recording folder")
    parts = parse_name(folder)
    where = folder.name
    json_path = folder / f"{folder.name}.json"
    if not json_path.is_file():
        raise RecordingError(f"{folder}: missing {json_path.name}")
    meta = read_json(json_path, "iPhUMI recording")
    if not isinstance(meta, dict):
        raise RecordingError(f"{json_path}: must hold a JSON object")
    missing = [key for key in ("poseTimes", "rgbTimes", "ultrawideRGBTimes", "poseTransforms") if key not in meta]
    if missing:
        raise RecordingError(f"{json_path}: missing {', '.join(missing)}")
    calibration = parts["kind"] == "grippercalibration"
    pose_times = parse_times(meta["poseTimes"], "poseTimes", where)
    if len(pose_times) < 2 and not calibration:  # a gripper calibration records the ultrawide camera alone
        raise RecordingError(f"{where}: {len(pose_times)} pose(s); a demonstration needs at least two")
    poses = _matrices(meta["poseTransforms"], len(pose_times), (4, 4), "poseTransforms", where)
    rotations = poses[:, :3, :3]
    orthogonal = np.abs(rotations @ np.swapaxes(rotations, 1, 2) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    not_rigid = (orthogonal > 1e-3) | (np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1, initial=0.0) > 1e-6)
    if np.any(not_rigid):
        first = int(np.argmax(not_rigid))
        raise RecordingError(
            f"{where}: poseTransforms[{first}] is not a rigid transform (row-major 4x4, rotation then translation "
            "column, last row 0 0 0 1)"
        )
    rgb_times = parse_times(meta["rgbTimes"], "rgbTimes", where)
    ultrawide = parse_times(meta["ultrawideRGBTimes"], "ultrawideRGBTimes", where, allow_missing=True)
    depth_times = parse_times(meta.get("depthTimes", []), "depthTimes", where)
    intrinsics = {}
    for key in ("mainCameraIntrinsics", "ultrawideCameraIntrinsics"):
        if key not in meta:
            raise RecordingError(f"{json_path}: missing {key}")
        matrix = _matrices([meta[key]] if np.ndim(meta[key]) in (1, 2) else meta[key], 1, (3, 3), key, where)[0]
        if not (matrix[0, 0] > 0 and matrix[1, 1] > 0 and np.allclose(matrix[2], [0, 0, 1])):
            raise RecordingError(f"{where}: {key} is not a camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]")
        intrinsics[key] = matrix
    recording = Recording(
        folder=folder,
        name=folder.name,
        meta=meta,
        pose_times=pose_times,
        poses=poses,
        rgb_times=rgb_times,
        ultrawide_times=ultrawide,
        depth_times=depth_times,
        main_intrinsics=intrinsics["mainCameraIntrinsics"],
        ultrawide_intrinsics=intrinsics["ultrawideCameraIntrinsics"],
        labels=_labels(meta, where),
        **parts,
    )
    for key, value in (("type", recording.kind), ("side", recording.side)):
        if key in meta and str(meta[key]).replace("_", "") != value:
            raise RecordingError(f"{where}: the JSON's {key} {meta[key]!r} contradicts the folder name's {value!r}")
    if not np.any(~np.isnan(ultrawide)) and recording.side != "head":
        raise RecordingError(f"{where}: ultrawideRGBTimes names no frame; the gripper's width is read from them")
    if check_media:
        for path in (recording.ultrawide_path,) if calibration else (recording.rgb_path, recording.ultrawide_path):
            if not path.is_file():
                raise RecordingError(f"{folder}: missing {path.name}")
    return recording


def _labels(meta: dict, where: str) -> tuple[TaskLabel, ...]:
    names = meta.get("taskNames") or []
    starts, ends = meta.get("taskStartTimestamps") or [], meta.get("taskEndTimestamps") or []
    if not (len(names) == len(starts) == len(ends)):
        raise RecordingError(
            f"{where}: taskNames, taskStartTimestamps and taskEndTimestamps must have one entry per label, got "
            f"{len(names)}, {len(starts)} and {len(ends)}"
        )
    labels = []
    for i, (name, start, end) in enumerate(zip(names, starts, ends, strict=True)):
        try:
            label = TaskLabel(str(name).strip(), parse_time(start), parse_time(end))
        except (ValueError, TypeError):
            raise RecordingError(f"{where}: task label {i} ({name!r}) has an unparsable start or end time") from None
        if not label.name or label.end <= label.start:
            raise RecordingError(f"{where}: task label {i} ({name!r}) is empty or ends before it starts")
        labels.append(label)
    return tuple(labels)


# ------------------------------------------------------------------------------------------------ an export
RECORDING_FILE = re.compile(r"(_rgb\.mp4|_ultrawidergb\.mp4|_depth\.raw)$")
"""How the app names a recording's videos and depth (the JSON is ``<name>.json``)."""


def scan_export(export: str | Path) -> tuple[list[Path], list[tuple[Path, str]]]:
    """Every recording folder under `export` (sorted by path) and [(folder, why it is left out)] for every folder
    that looks like a recording but cannot be read as one: named as a recording but without its JSON, or holding a
    recording's files under a name that is not a recording's. Hidden folders (a store's parts) are not looked in."""
    export = Path(export)
    if not export.is_dir():
        raise UserError(f"{export}: no such folder of iPhUMI recordings")
    found, left_out = [], []
    for folder, files in _folders(export):
        if NAME.match(folder.name) and f"{folder.name}.json" in files:
            found.append(folder)
        elif (reason := _not_a_recording(folder, files)) is not None:
            left_out.append((folder, reason))
    return found, left_out


def _folders(export: Path):
    """(folder, the names of its files) of `export` and every folder under it, sorted by path; hidden folders and
    files (a store's parts, a Mac's ``._`` files) left aside."""
    found, seen = [], set()
    for root, dirs, files in os.walk(export, followlinks=True):
        real = os.path.realpath(root)
        if real in seen:  # a linked folder is looked in once (a link to a folder above it would loop)
            dirs.clear()
            continue
        seen.add(real)
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        found.append((Path(root), sorted(f for f in files if not f.startswith("."))))
    return sorted(found)


def _not_a_recording(folder: Path, files: list[str]) -> str | None:
    """Why a folder that is not a readable recording looks like one, or None if it looks like none."""
    stems = [f[:-5] for f in files if f.endswith(".json") and NAME.match(f[:-5])]
    shown = ", ".join(files[:4]) + (f" and {len(files) - 4} more" if len(files) > 4 else "")
    if NAME.match(folder.name):
        return f"missing {folder.name}.json ({'it holds ' + shown if files else 'the folder is empty'})"
    if not stems and not any(RECORDING_FILE.search(f) for f in files):
        return None
    hint = f"; rename the folder {stems[0]}, as its files are named" if stems else ""
    return f"not an iPhUMI recording folder name ({EXPECTED_NAME}) but it holds recording files ({shown}){hint}"


def find_recordings(export: str | Path) -> list[Path]:
    """Every recording folder under `export`, sorted by path (:func:`scan_export` also says which are left out)."""
    return scan_export(export)[0]


def index_recordings(folders: list[Path]) -> dict[str, Path]:
    """Recording name -> folder. Two folders of one name (a recording exported twice, or renamed alike) are refused,
    naming both: recordings are found by name, so either could be taken for the other."""
    index: dict[str, Path] = {}
    for folder in folders:
        other = index.setdefault(folder.name, folder)
        if other.resolve() != folder.resolve():
            raise RecordingError(
                f"two recordings are named {folder.name}: {other} and {folder}; a recording's name must be unique "
                "in an export (remove or move one of them)"
            )
    return index


@dataclass
class Demonstration:
    """The recordings of one demonstration: one per phone (right and/or left gripper, optionally the head)."""

    group: str
    phones: dict[str, Recording]

    @property
    def grippers(self) -> list[str]:
        """The sides holding a gripper, the right first."""
        return [side for side in ("right", "left") if side in self.phones]


def group_demonstrations(recordings: list[Recording]) -> tuple[list[Demonstration], list[tuple[str, str]]]:
    """Demonstration recordings grouped by name -> (complete demonstrations, [(group, why it is invalid)]): a
    demonstration missing a side its phones list in ``sidesPresent`` is invalid, as is one without a gripper phone."""
    groups: dict[str, dict[str, Recording]] = {}
    for recording in recordings:
        if recording.kind == "demonstration":
            other = groups.setdefault(recording.group, {}).setdefault(recording.side, recording)
            if other is not recording:
                raise RecordingError(
                    f"two recordings are the {recording.side} phone of {recording.group}: {other.folder} and "
                    f"{recording.folder}; remove or move one of them"
                )
    valid, invalid = [], []
    for group, phones in sorted(groups.items()):
        listed = {side for r in phones.values() for side in r.sides_present}
        missing = sorted(listed - set(phones))
        if missing:
            invalid.append((group, f"the side(s) {', '.join(missing)} listed in sidesPresent have no recording"))
        elif not ({"right", "left"} & set(phones)):
            invalid.append((group, "no gripper phone (only the head)"))
        else:
            valid.append(Demonstration(group, phones))
    return valid, invalid
