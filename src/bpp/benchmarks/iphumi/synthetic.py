"""Synthetic iPhUMI exports with known ground truth (``bpp iphumi synth``): for tests, docs and benchmarks.

A recording is written exactly as the phone app exports it (:mod:`bpp.benchmarks.iphumi.recording`). Each task is a
procedural DrawAnything drawing traced by the gripper on a table: the gripper closes on a marker, draws the strokes
(lifting between them), and opens again. Per demonstration the drawing's placement on the table varies, and each
phone's ARKit world frame is a random rigid transform of the table's, as a new ARKit session's would be. Poses are
exact at the logged (millisecond) times; ultrawide frames (10 Hz) show the finger tags drawn by OpenCV at the true
gripper width; main-camera frames show the ink so far and the pen; depth (optional) is a tilted plane.

With ``canvas``, each drawing is traced on DrawAnything-Real's marked canvas (:mod:`bpp.drawing.marked_canvas`)
lying on the table, at the size the arm draws it, and each task begins with the phone held still high above the
canvas: the main camera's frames then are exact photos of the canvas and its four red markers (the frames after
them stay schematic), from which ``bpp iphumi process --canvas`` measures where the canvas lies.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bpp.benchmarks.iphumi import gripper
from bpp.benchmarks.iphumi.align import MOUNTS
from bpp.benchmarks.iphumi.recording import DEPTH_SHAPE, find_recordings
from bpp.benchmarks.iphumi.video import write_video
from bpp.core.poses import invert, make_pose
from bpp.drawing.drawing import Drawing
from bpp.drawing.human import HUMAN_GLYPHS, human_drawings
from bpp.drawing.marked_canvas import DRAW_SIDE, render_canvas
from bpp.drawing.procedural import ProceduralConfig, generate_drawing
from bpp.errors import UserError
from bpp.utils import atomic_path, check_fields

DEVICE = "iPhone16,1"
CLOSED_WIDTH = 0.025
"""The finger tags' spacing with the gripper closed (m); the width the processing reports is the spacing minus this."""
OPEN_WIDTH = 0.06
"""How far the synthetic gripper opens (m)."""
ULTRAWIDE_K = np.array([[360.0, 0.0, 320.0], [0.0, 360.0, 240.0], [0.0, 0.0, 1.0]])
ULTRAWIDE_EVERY = 6
"""One ultrawide frame per this many 60 Hz frames (10 Hz)."""
CANVAS = 0.2
"""Side of the square a drawing is traced in (m)."""
HOVER, LIFT = 0.08, 0.015
"""Heights above the table (m): approaching and leaving, and lifted between strokes."""
SPEED = 0.12
"""Tracing speed (m/s)."""
MAIN_SIDES = (16, 4096)
"""The smallest and largest side of the main camera's video (px)."""
LOOK = 0.35
"""With a canvas: the pen's height above the canvas's centre while the phone looks at it (m); the main camera, some
0.55 m away, then sees the whole canvas."""
CANVAS_MAIN_SIZE = (320, 240)
"""With a canvas: the smallest main-camera video that resolves its markers (px)."""
TABLE_FROM_CANVAS = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
"""A canvas-frame direction (x right, y up the drawing, z out of the table) in the table frame (x, z on the table, y
up)."""


@dataclass(frozen=True)
class SyntheticSettings:
    """What ``bpp iphumi synth`` writes."""

    demonstrations: int = 4
    tasks: int = 2
    """Distinct tasks (drawings); demonstration i performs task i mod tasks (and the next ones, see below)."""
    tasks_per_demonstration: int = 1
    """Labelled task segments per demonstration."""
    bimanual: bool = False
    """Two gripper phones (right and left) per demonstration, in one shared world frame."""
    head: bool = False
    """A head-mounted phone too."""
    depth: bool = False
    """Record LiDAR depth (192x256 float16 per 60 Hz frame: 6 MB a second)."""
    main_size: tuple[int, int] = (160, 120)
    """Main camera video (width, height), even numbers of pixels (H.264) in [16, 4096]; the app records 1920x1440."""
    canvas: bool = False
    """Trace each drawing on DrawAnything-Real's marked canvas, the phone first held above it (single arm)."""
    drawings: str = "procedural"
    """procedural (DrawAnything's generator) or human (its 50 human-made drawings: task i draws the i-th)."""
    session: str = "synthetic"
    """The data-collection session's name, part of every folder name: letters, digits, '.' and '-'."""
    seed: int = 0

    def __post_init__(self):
        check_fields(
            self,
            ("demonstrations", self.demonstrations >= 1, ">= 1"),
            ("tasks", self.tasks >= 1, ">= 1"),
            ("tasks_per_demonstration", self.tasks_per_demonstration >= 1, ">= 1"),
            (
                "main_size",
                len(self.main_size) == 2
                and all(MAIN_SIDES[0] <= v <= MAIN_SIDES[1] and v % 2 == 0 for v in self.main_size),
                f"a width and a height, even numbers of pixels in [{MAIN_SIDES[0]}, {MAIN_SIDES[1]}]",
            ),
            (
                "session",
                re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9.-]*", self.session) is not None,
                "a name of letters, digits, '.' and '-' (no '_' or '/': it is part of the folder names)",
            ),
            ("seed", self.seed >= 0, ">= 0"),
            ("canvas", not (self.canvas and (self.bimanual or self.head)), "without --bimanual and --head"),
            ("drawings", self.drawings in ("procedural", "human"), "procedural or human"),
            (
                "main_size",
                not self.canvas or all(v >= m for v, m in zip(self.main_size, CANVAS_MAIN_SIZE, strict=True)),
                f"at least {CANVAS_MAIN_SIZE[0]}x{CANVAS_MAIN_SIZE[1]} with --canvas (the markers must be resolved)",
            ),
        )


@dataclass
class Truth:
    """Ground truth of one phone's recording, at its logged pose times."""

    times: np.ndarray
    tcp: np.ndarray
    """(N, 4, 4) the TCP in the phone's world frame."""
    width: np.ndarray
    """(N,) the gripper opening (m, 0 closed)."""
    labels: list = field(default_factory=list)
    motion: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = field(default=None, repr=False)
    """The motion itself: epoch times (M,) -> (TCP poses (M, 4, 4), openings (M,)) at any time, not only logged ones."""
    canvas: np.ndarray | None = None
    """With a canvas: its pose (4, 4) in the phone's world frame."""


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _folder_time(t: float) -> str:
    return _iso(t).replace(":", "-")


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def task_drawing(task: int, seed: int, drawings: str = "procedural") -> tuple[str, Drawing]:
    """Task `task`'s (label, drawing): a procedural one of `seed`, or DrawAnything's human-made drawing number
    `task` (of 50, cyclically)."""
    if drawings == "human":
        drawing = human_drawings()[task % len(HUMAN_GLYPHS)]
        return f"draw {drawing.id}", drawing
    drawing, _ = generate_drawing(np.random.default_rng([seed, task]), ProceduralConfig(max_parts=3), f"task{task}")
    return f"draw task {task}", drawing


def _task_path(drawing: Drawing, canvas: bool = False) -> np.ndarray:
    """A drawing traced: positions (M, 3) in the canvas frame (x, y on the table, z up), the pen lifted between
    strokes. With `canvas`, at the marked canvas's drawing size, from a look at it."""
    side = DRAW_SIDE if canvas else CANVAS
    points = [np.array([0.5, 0.5, LOOK / side])] if canvas else []
    points.append(np.array([0.5, 0.5, HOVER / side]))
    for stroke in drawing.strokes:
        points += [np.append(stroke[0], LIFT / side), *(np.append(p, 0.0) for p in stroke)]
        points.append(np.append(stroke[-1], LIFT / side))
    points.append(np.array([0.5, 0.5, HOVER / side]))
    return (np.asarray(points) - [0.5, 0.5, 0.0]) * side


def _trace(path: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Positions along `path` at `times` (seconds from the segment's start) at SPEED, holding the end."""
    lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arrival = np.concatenate([[0.0], np.cumsum(lengths) / SPEED])
    return np.stack([np.interp(times, arrival, path[:, i]) for i in range(3)], axis=-1)


def _segment_seconds(path: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) / SPEED)


GRASP = 0.5
"""Seconds the gripper takes to close at a segment's start (and to open at its end)."""


def _opening(local: np.ndarray, duration: float) -> np.ndarray:
    """The gripper opening over a segment: closing on the marker, closed while drawing, opening at the end."""
    closing = np.clip(1 - local / GRASP, 0, 1)
    opening = np.clip((local - (duration - GRASP)) / GRASP, 0, 1)
    return OPEN_WIDTH * np.maximum(closing, opening)


def write_export(out: str | Path, settings: SyntheticSettings = SyntheticSettings()) -> dict[str, Truth]:
    """Write a synthetic export into `out` (a day folder per date, as the app exports) -> the ground truth of every
    demonstration recording, by folder name. Each gripper side gets one calibration recording."""
    rng = np.random.default_rng(settings.seed)
    out = Path(out)
    if out.is_dir() and (earlier := find_recordings(out)):
        raise UserError(
            f"{out} already holds {len(earlier)} iPhUMI recording(s); synth writes into a new or empty folder, so that "
            "no recording is overwritten"
        )
    day = datetime(2026, 1, 15, 9, 0, 0, tzinfo=timezone.utc)
    out.mkdir(parents=True, exist_ok=True)
    # The day's folder is written as a whole or not at all (a full disk, Ctrl-C), the error naming it.
    with atomic_path(out / day.strftime("%Y-%m-%d")) as folder:
        truths: dict[str, Truth] = {}
        sides = ["right", "left"] if settings.bimanual else ["right"]
        calibrations = {}
        clock = day.timestamp()
        for side in sides:
            name = f"{_folder_time(clock)}_{rng.integers(10000, 99999)}_{settings.session}_grippercalibration_{side}"
            _write_calibration(folder / name, clock, side, settings, rng)
            calibrations[side] = name
            clock += 20.0
        for demo in range(settings.demonstrations):
            clock += 5.0
            tasks = [(demo + k) % settings.tasks for k in range(settings.tasks_per_demonstration)]
            turn = _rotation_y(rng.uniform(-0.5, 0.5))
            place = make_pose(turn, [rng.uniform(-0.1, 0.1), 0.0, rng.uniform(-0.1, 0.1)])
            # the motion, shared by the phones of a bimanual demonstration (the left gripper mirrors the right at an
            # offset)
            local, positions, labels, widths, looking, t = [], [], [], [], [], 0.0
            for task in tasks:
                label, drawing = task_drawing(task, settings.seed, settings.drawings)
                path = _task_path(drawing, settings.canvas)
                duration = _segment_seconds(path) + 2 * GRASP
                steps = np.arange(0.0, duration, 1 / 60)
                positions.append(_trace(path, np.clip(steps - GRASP, 0, None)))
                widths.append(_opening(steps, duration))
                looking.append(steps < GRASP if settings.canvas else np.zeros(len(steps), bool))
                labels.append((label, t, t + duration))
                local.append(t + steps)
                t += duration + 0.5
            number = rng.integers(10000, 99999)
            group = f"{_folder_time(clock)}_{number}_{settings.session}_demonstration"
            present = [*sides, "head"] if settings.head else sides
            # the phones' shared ARKit world frame: a random rigid transform of the table's, as a new session's is
            world = make_pose(_rotation_y(rng.uniform(-np.pi, np.pi)), rng.normal(0, 0.5, 3))
            canvas = world @ place @ make_pose(TABLE_FROM_CANVAS, np.zeros(3)) if settings.canvas else None
            for side in present:
                offset = {"right": 0.0, "left": -0.35, "head": -0.15}[side]
                jitter = rng.uniform(-0.4, 0.4, size=sum(len(p) for p in positions)) * 1e-3
                times = np.round((clock + np.concatenate(local) + jitter) * 1000) / 1000
                motion = _motion(clock, positions, local, widths, world @ place, offset, side)
                tcp, width = motion(times)
                name = f"{group}_{side}"
                _write_demonstration(
                    folder / name,
                    times,
                    tcp,
                    width,
                    labels,
                    clock,
                    side,
                    present,
                    calibrations.get(side, ""),
                    tasks,
                    settings,
                    rng,
                    (canvas, np.concatenate(looking)),
                )
                if side != "head":
                    spans = [(n, clock + a, clock + b) for n, a, b in labels]
                    truths[name] = Truth(times, tcp, width, spans, motion, canvas)
            clock += t + 2.0
    return truths


def _motion(clock, positions, local, widths, place, offset, side):
    """The demonstration's motion as a function of epoch time."""

    def at(times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seconds = np.asarray(times, dtype=np.float64) - clock
        width = np.interp(seconds, np.concatenate(local), np.concatenate(widths))
        return _tcp_poses(seconds, positions, local, place, offset, side), width

    return at


def _tcp_poses(times, positions, local, place, offset, side) -> np.ndarray:
    """TCP poses at `times` (seconds from the demonstration's start): the traced positions on the table (table frame:
    x, z on the table, y up, as ARKit's gravity-aligned world), pointing down, with a slow wobble."""
    path = np.concatenate(positions)
    at = np.stack([np.interp(times, np.concatenate(local), path[:, i]) for i in range(3)], axis=-1)
    table = np.stack([at[:, 0] + offset, at[:, 2] + (0.3 if side == "head" else 0.0), -at[:, 1]], axis=-1)
    down = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # TCP x = table x, z (forward) = down
    wobble = np.stack([_axis_angle([1.0, 0, 0], 0.15 * np.sin(0.7 * t)) for t in times])
    return place @ make_pose(down @ wobble, table)


def _axis_angle(axis, angle: float) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(axis) / np.linalg.norm(axis) * angle).as_matrix()


def _base_meta(name: str, start: float, side: str, settings: SyntheticSettings, kind: str) -> dict:
    return {
        "formatVersion": "v1",
        "recordingStartTime": _iso(start),
        "side": side,
        "type": kind,
        "sessionName": settings.session,
        "gripperID": "default",
        "deviceName": "iPhone 15 Pro",
        "deviceIdentifier": DEVICE,
        "mainCameraIntrinsics": _main_k(settings).tolist(),
        "ultrawideCameraIntrinsics": ULTRAWIDE_K.tolist(),
        "labelType": "None",
        "taskNames": [],
        "taskStartTimestamps": [],
        "taskEndTimestamps": [],
        "isErrorCorrection": False,
        "hasAudio": False,
    }


def _main_k(settings: SyntheticSettings) -> np.ndarray:
    w, h = settings.main_size
    return np.array([[0.9 * w, 0.0, w / 2], [0.0, 0.9 * w, h / 2], [0.0, 0.0, 1.0]])


def _write_calibration(folder: Path, start: float, side: str, settings: SyntheticSettings, rng) -> None:
    """About 10 s of the gripper opening and closing five times, seen by the ultrawide camera alone."""
    folder.mkdir(parents=True, exist_ok=True)
    count = 600
    times = start + np.arange(count) / 60
    shown = np.arange(count) % ULTRAWIDE_EVERY == 0
    opening = OPEN_WIDTH * 0.5 * (1 - np.cos(2 * np.pi * (times[shown] - start) / 2.0))
    tags = side if settings.bimanual else "right"
    frames = [gripper.render_fingers(CLOSED_WIDTH + w, ULTRAWIDE_K, tags, rng=rng) for w in opening]
    write_video(folder / f"{folder.name}_ultrawidergb.mp4", frames, 10, (640, 480))
    meta = _base_meta(folder.name, start, side, settings, "gripper_calibration")
    meta.update(
        poseTimes=[],
        poseTransforms=[],
        rgbTimes=[],
        depthTimes=[],
        hasRGB=False,
        hasDepth=False,
        hasUltrawideRGB=True,
        sidesPresent=[side],
        gripperCalibrationRunName="",
        frameCount=count,
        ultrawideRGBTimes=[_iso(t) if s else "" for t, s in zip(times, shown, strict=True)],
    )
    (folder / f"{folder.name}.json").write_text(__import__("json").dumps(meta))


def _write_demonstration(
    folder, times, tcp, width, labels, clock, side, present, calibration, tasks, settings, rng, canvas=(None, None)
):
    folder.mkdir(parents=True, exist_ok=True)
    mount = MOUNTS[DEVICE] if side != "head" else make_pose(np.diag([1.0, -1.0, -1.0]), [0, 0, 0])
    camera = tcp @ invert(mount)
    shown = np.arange(len(times)) % ULTRAWIDE_EVERY == 0
    strings = [_iso(t) for t in times]
    meta = _base_meta(folder.name, times[0], side, settings, "demonstration")
    meta.update(
        poseTimes=strings,
        poseTransforms=camera.tolist(),
        rgbTimes=strings,
        ultrawideRGBTimes=[s if k else "" for s, k in zip(strings, shown, strict=True)],
        depthTimes=strings if settings.depth else [],
        depthFrameIsRepeat=[False] * len(times) if settings.depth else [],
        hasRGB=True,
        hasUltrawideRGB=True,
        hasDepth=settings.depth,
        sidesPresent=list(present),
        gripperCalibrationRunName=calibration,
        frameCount=len(times),
        labelType="Predefined",
        taskNames=[n for n, _, _ in labels],
        taskStartTimestamps=[_iso(clock + a) for _, a, _ in labels],
        taskEndTimestamps=[_iso(clock + b) for _, _, b in labels],
    )
    tags = side if settings.bimanual else "right"
    if side != "head":
        uw = [gripper.render_fingers(CLOSED_WIDTH + w, ULTRAWIDE_K, tags, rng=rng) for w in width[shown]]
        write_video(folder / f"{folder.name}_ultrawidergb.mp4", uw, 10, (640, 480))
    else:
        write_video(
            folder / f"{folder.name}_ultrawidergb.mp4",
            [np.zeros((480, 640, 3), np.uint8)] * int(shown.sum()),
            10,
            (640, 480),
        )
    frames = _main_frames(tcp, width, settings, tasks, camera, *canvas, rng)
    write_video(folder / f"{folder.name}_rgb.mp4", frames, 60, settings.main_size)
    if settings.depth:
        plane = 0.25 + 0.1 * np.linspace(0, 1, DEPTH_SHAPE[0])[:, None] + np.zeros(DEPTH_SHAPE)
        with open(folder / f"{folder.name}_depth.raw", "wb") as f:
            for k in range(len(times)):
                f.write((plane + 0.01 * np.sin(k / 30)).astype("<f2").tobytes())
    (folder / f"{folder.name}.json").write_text(__import__("json").dumps(meta))


def _main_frames(tcp, width, settings, tasks, camera, canvas, looking, rng):
    """The main camera's frames: the ink drawn so far (where the pen touched the table) and the pen, seen from above,
    on a background whose colour names the demonstration's first task; while `looking` (a mask over frames), an exact
    photo of the `canvas` (its pose in the world) from the `camera` (ARKit's camera poses)."""
    # OpenCV: the iphumi extra
    import cv2

    w, h = settings.main_size
    base = np.zeros((h, w, 3), np.uint8)
    base[:] = (60 + 40 * (tasks[0] % 4), 120, 200 - 30 * (tasks[0] % 5))
    start = tcp[0, :3, 3]
    ink = base.copy()
    scale = min(w, h) / (CANVAS * 1.6)
    opencv = np.diag([1.0, -1.0, -1.0, 1.0])  # ARKit's camera axes (y up, z back) -> OpenCV's (y down, z forward)
    for k, pose in enumerate(tcp):
        offset = pose[:3, 3] - start
        x, y = int(w / 2 + offset[0] * scale), int(h / 2 + offset[2] * scale)
        if pose[1, 3] - tcp[:, 1, 3].min() < 0.002:
            cv2.circle(ink, (x, y), 1, (20, 20, 20), -1)
        if canvas is not None and looking[k]:
            yield render_canvas(invert(camera[k] @ opencv) @ canvas, _main_k(settings), (w, h), rng=rng)
            continue
        frame = ink.copy()
        cv2.circle(frame, (x, y), 3, (230, 40, 40), -1)
        yield frame
