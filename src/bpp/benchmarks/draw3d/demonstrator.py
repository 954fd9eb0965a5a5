"""The scripted drawing demonstrator of DrawAnything-Real, as the paper describes it: from a random pose in front of
the board, start recording, move to the canvas, align the pen with it, draw the strokes with pen lifts along the
board's normal, and retreat to a random pose. Open loop: the plan is a sequence of commanded pen poses computed
from the canvas pose alone (estimated from a photo, as a lab would), and its actions are the relative steps between
them, so the recorded actions replay the same commands exactly.

A demonstration is judged by the ink it leaves: its Chamfer distance to the drawing, in DrawAnything's pixels
(:func:`ink_chamfer`), must be under a threshold, else it is counted as a failure and not stored.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from bpp.benchmarks.draw3d.scene import Scene
from bpp.core.poses import invert, make_pose, pose_to_vector
from bpp.drawing.geometry import BOARD_SIZE, unit_to_canvas
from bpp.drawing.marked_canvas import DRAW_SIDE, canvas_to_drawing, drawing_to_canvas
from bpp.drawing.metric import chamfer_distance, ink_mask
from bpp.utils import check_fields

DOWN = np.diag([1.0, -1.0, -1.0])
"""The pen's orientation in the canvas frame when drawing: into the canvas, its x along the canvas's x."""


@dataclass(frozen=True)
class ScriptConfig:
    """The scripted demonstrator's motion (metres, seconds)."""

    draw_speed: tuple[float, float] = (0.06, 0.10)
    """Pen speed while drawing (m/s), drawn once per demonstration."""
    travel_speed: float = 0.15
    """Speed of the pen in the air (m/s)."""
    turn_speed_deg: float = 90.0
    """Most rotation per second while aligning with the canvas."""
    lift: float = 0.012
    """Height of a pen lift between strokes (m)."""
    press: float = 0.001
    """How far past the surface the pen is commanded while drawing: the spring's compression (m)."""
    start_distance: tuple[float, float] = (0.07, 0.14)
    """Range of the random start and retreat poses' distance from the canvas (m)."""
    start_offset: float = 0.08
    """Most offset of the random start and retreat poses along the canvas from its centre (m)."""
    start_tilt_deg: float = 20.0
    """Most tilt of the random start and retreat poses from the drawing orientation."""
    settle_steps: int = 2
    """Control steps held still at a stroke's start and end."""

    def __post_init__(self):
        lo, hi = self.draw_speed
        check_fields(
            self,
            ("draw_speed", 0 < lo <= hi <= 0.5, "lo, hi with 0 < lo <= hi <= 0.5 m/s"),
            ("travel_speed", 0 < self.travel_speed <= 1, "in (0, 1] m/s"),
            ("lift", 0.002 < self.lift <= 0.1, "in (0.002, 0.1] m"),
            ("press", 0 <= self.press <= 0.002, "in [0, 0.002] m (within the pen's spring)"),
        )


@dataclass
class Plan:
    """Commanded pen poses in the canvas frame (T_canvas_pen), one per control step, the first the start pose."""

    poses: list = field(default_factory=list)

    def to(self, goal: np.ndarray, speed: float, turn_speed_deg: float, hz: float) -> None:
        """Append poses moving straight to `goal` at `speed` (positions) and at most the turn speed (rotations)."""
        start = self.poses[-1]
        distance = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
        turn = float(np.rad2deg(Rotation.from_matrix(start[:3, :3].T @ goal[:3, :3]).magnitude()))
        steps = max(1, int(np.ceil(max(distance / speed, turn / turn_speed_deg) * hz)))
        spin = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([start[:3, :3], goal[:3, :3]])))
        for k in range(1, steps + 1):
            a = k / steps
            self.poses.append(make_pose(spin(a).as_matrix(), (1 - a) * start[:3, 3] + a * goal[:3, 3]))

    def trace(self, points: np.ndarray, height: float, speed: float, hz: float) -> None:
        """Append poses along a polyline (N, 2) at `height`, evenly spaced at `speed`, ending at its last point."""
        lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        steps = max(1, int(np.ceil(lengths[-1] / speed * hz)))
        at = np.linspace(0.0, lengths[-1], steps + 1)[1:]
        for x, y in zip(np.interp(at, lengths, points[:, 0]), np.interp(at, lengths, points[:, 1]), strict=True):
            self.poses.append(make_pose(DOWN, [x, y, height]))

    def hold(self, steps: int) -> None:
        self.poses += [self.poses[-1]] * steps


def random_pose(rng: np.random.Generator, cfg: ScriptConfig) -> np.ndarray:
    """A random pen pose in front of the canvas (canvas frame): tilted from the drawing orientation, offset along it."""
    axis = rng.normal(size=3)
    tilt = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(0, cfg.start_tilt_deg)))
    position = [*rng.uniform(-cfg.start_offset, cfg.start_offset, 2), rng.uniform(*cfg.start_distance)]
    return make_pose(DOWN @ tilt.as_matrix(), position)


def plan_drawing(strokes, rng: np.random.Generator, cfg: ScriptConfig, hz: float) -> Plan:
    """The commanded poses (canvas frame) drawing `strokes` (unit-square polylines, y up) from a random start to a
    random retreat."""
    plan = Plan([random_pose(rng, cfg)])
    speed = rng.uniform(*cfg.draw_speed)
    for stroke in strokes:
        points = drawing_to_canvas(stroke)
        plan.to(make_pose(DOWN, [*points[0], cfg.lift]), cfg.travel_speed, cfg.turn_speed_deg, hz)
        plan.to(make_pose(DOWN, [*points[0], -cfg.press]), cfg.travel_speed / 3, cfg.turn_speed_deg, hz)
        plan.hold(cfg.settle_steps)
        plan.trace(points, -cfg.press, speed, hz)
        plan.hold(cfg.settle_steps)
        plan.to(make_pose(DOWN, [*points[-1], cfg.lift]), cfg.travel_speed / 3, cfg.turn_speed_deg, hz)
    plan.to(random_pose(rng, cfg), cfg.travel_speed, cfg.turn_speed_deg, hz)
    return plan


def actions_of(plan: Plan) -> np.ndarray:
    """(T - 1, 10) relative actions between a plan's consecutive poses, and a zero gripper command (the pen is
    held). Frame-independent: the same in the canvas frame as in the base frame."""
    poses = np.stack(plan.poses)
    steps = invert(poses[:-1]) @ poses[1:]
    return np.concatenate([pose_to_vector(steps), np.zeros((len(steps), 1))], axis=1)


@dataclass
class Recorded:
    """A demonstration as executed: per step (before its action) the pen's pose in the base frame, the ink's length
    so far and whether the pen touches; the actions; the ink; and optionally camera frames."""

    tip: np.ndarray
    tip_in_canvas: np.ndarray
    """The pen tip's pose in the frame of the canvas pose the plan was made in (9 per step)."""
    targets_in_canvas: np.ndarray
    """The commanded pen pose each action leads to, in that frame (9 per step): the actions as absolute poses."""
    ink_length: np.ndarray
    pen_down: np.ndarray
    actions: np.ndarray
    strokes: list
    frames: dict = field(default_factory=dict)


def execute(
    scene: Scene,
    canvas_estimate: np.ndarray,
    plan: Plan,
    cameras: tuple[str, ...] = (),
    approach_steps: int = 0,
) -> Recorded:
    """Run a plan made in the frame of `canvas_estimate` (the canvas pose a photo gave, ``T_base_canvas``) on a scene
    already reset: the arm first moves, unrecorded, to the plan's start pose (`approach_steps` control steps, 0 for a
    speed-limited count), then recording starts."""
    execute_approach(scene, canvas_estimate @ plan.poses[0], approach_steps)
    scene.ink.strokes.clear()
    scene.ink.down = False
    actions = actions_of(plan)
    to_canvas = invert(canvas_estimate)
    tips, tips_in_canvas, targets, lengths, downs = [], [], [], [], []
    frames: dict[str, list] = {camera: [] for camera in cameras}
    for action in actions:
        tip = scene.tip_pose()
        tips.append(pose_to_vector(tip))
        tips_in_canvas.append(pose_to_vector(to_canvas @ tip))
        lengths.append(scene.ink.length)
        downs.append(float(scene.ink.down))
        for camera in cameras:
            frames[camera].append(scene.render(camera))
        scene.step(action)
        targets.append(pose_to_vector(to_canvas @ scene.target))
    return Recorded(
        tip=np.asarray(tips, dtype=np.float32),
        tip_in_canvas=np.asarray(tips_in_canvas, dtype=np.float32),
        targets_in_canvas=np.asarray(targets, dtype=np.float32),
        ink_length=np.asarray(lengths, dtype=np.float32)[:, None],
        pen_down=np.asarray(downs, dtype=np.float32)[:, None],
        actions=actions,
        strokes=scene.ink.polylines(),
        frames={camera: np.stack(f) for camera, f in frames.items()},
    )


def execute_approach(scene: Scene, start: np.ndarray, steps: int = 0) -> None:
    """Move the pen, unrecorded, straight to `start` (``T_base_pen``) at about 10 cm/s (or in `steps` control
    steps), then hold still for half a second."""
    steps = steps or max(10, int(np.linalg.norm(start[:3, 3] - scene.target[:3, 3]) / 0.1 * 20))
    origin = scene.target.copy()
    spin = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([origin[:3, :3], start[:3, :3]])))
    for k in range(1, steps + 1):
        a = k / steps
        waypoint = make_pose(spin(a).as_matrix(), (1 - a) * origin[:3, 3] + a * start[:3, 3])
        scene.step(np.append(pose_to_vector(invert(scene.target) @ waypoint), 0.0))
    for _ in range(10):
        scene.step(np.append(pose_to_vector(np.eye(4)), 0.0))


def ink_chamfer(strokes_m, drawing_strokes) -> float:
    """The Chamfer distance (DrawAnything's metric and pixels: the drawing's unit square is its 350-px board) between
    ink in the canvas frame (metres) and a drawing's unit-square strokes."""
    ink = [unit_to_canvas(canvas_to_drawing(s), 0.0) for s in strokes_m if len(s)]
    target = [unit_to_canvas(np.asarray(s), 0.0) for s in drawing_strokes]
    return chamfer_distance(ink_mask(target), ink_mask(ink))


def pixels_to_mm(pixels: float) -> float:
    """A distance in DrawAnything's pixels as millimetres on this canvas."""
    return pixels * DRAW_SIDE / BOARD_SIZE * 1000.0
