"""DrawAnything-Sim as a Gymnasium environment."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from bpp.benchmarks.draw import physics
from bpp.benchmarks.draw.render import SceneRenderer, upright_points
from bpp.benchmarks.draw.viz import TARGET_RGB, target_coverage
from bpp.drawing.drawing import Drawing
from bpp.drawing.geometry import (
    BOARD_CENTER,
    BOARD_SIZE,
    CANVAS_SIZE,
    MAX_BOARD_ANGLE,
    canvas_to_unit,
    canvas_to_upright,
    unit_to_canvas,
)
from bpp.drawing.metric import ChamferTracker, InkMask, ink_mask

ENV_ID = "bpp/DrawAnything-v0"
"""Its Gymnasium id (registered by ``import bpp.benchmarks``; see bpp.benchmarks.GYM_ENVS)."""
CURSOR_START_RANGE = (50.0, 450.0)
"""At reset the cursor rests at a uniformly random canvas position in this range on each axis, pen up."""
MAX_EPISODE_STEPS = 400
STILL_WINDOW = 20
STILL_RADIUS = 20.0


CAMERAS = ("image", "board_image")
"""The image observations the env can render: the canvas as a camera sees it, and the board's upright view."""
ACTION_FRAMES = {"action": "canvas", "action_on_board": "board"}
"""Stored action keys and the frame the environment must interpret them in (its ``action_frame``)."""


def ink_lengths(positions: np.ndarray, pen_down: np.ndarray) -> np.ndarray:
    """(T,) ink drawn before each of T states, in board sides: the summed length of every step that ended pen down.

    ``positions`` (T, 2) canvas px and ``pen_down`` (T,) of successive states; the ``ink_length`` observation.
    """
    step = np.linalg.norm(np.diff(np.asarray(positions, dtype=np.float64), axis=0), axis=-1)
    inked = step * (np.asarray(pen_down)[1:] > 0.5)
    return np.concatenate([[0.0], np.cumsum(inked)]) / BOARD_SIZE


def board_pose(angle: float) -> np.ndarray:
    """The low-dimensional board pose observation: (cos angle, sin angle), float32 (2,)."""
    return np.array([np.cos(angle), np.sin(angle)], dtype=np.float32)


def action_to_board(actions: np.ndarray, angle: float) -> np.ndarray:
    """Canvas actions (..., 3) ``[x, y, pen]`` -> board-frame actions: the target in the board's unit frame."""
    actions = np.asarray(actions, dtype=np.float64)
    return np.concatenate([canvas_to_unit(actions[..., :2], angle), actions[..., 2:]], axis=-1)


def action_to_canvas(actions: np.ndarray, angle: float) -> np.ndarray:
    """Inverse of :func:`action_to_board`."""
    actions = np.asarray(actions, dtype=np.float64)
    return np.concatenate([unit_to_canvas(actions[..., :2], angle), actions[..., 2:]], axis=-1)


class DrawEnv(gym.Env):
    """Draw on a rotated board with a PD-controlled cursor.

    Observation (a dict):
        ``image``      (R, R, 3) uint8, the camera's view of the canvas, rendered directly at ``image_size`` (absent
        if ``image_size`` is None or ``cameras`` leaves it out);
        ``board_image`` (R, R, 3) uint8, only if ``cameras`` names it: the same scene in the board's own frame,
        turned about the board's centre so that the board stands upright (its ink so far and the cursor where they
        are on the board): what a camera shows of the drawing, without the board's rotation, for policies that act
        in the board's frame;
        ``agent_pos``  (2,) float32 cursor position in canvas px;
        ``pen_down``   (1,) float32, 1 if the pen is down (the last action's pen);
        ``board_pose`` (2,) float32, (cos, sin) of the board angle;
        ``cursor_on_board`` (2,) float32, the cursor in the board's own unit frame (what the image shows: where
        the cursor is on the board), for state-only policies;
        ``ink_length`` (1,) float32, how much ink is on the board, in board sides (see :func:`ink_lengths`): the
        progress a camera sees as drawn ink, for state-only policies, which otherwise cannot tell a stroke's
        first pass from a later one.
    Action: (3,) ``[x, y, pen]`` — an absolute target in canvas px and a pen flag (down if > 0.5), as in the
    paper. With ``action_frame="board"`` the target is given in the board's unit frame instead (the frame of
    ``cursor_on_board``; stored demonstrations carry it as ``action_on_board``): a rotation-free representation
    for state-only policies, which then need not learn to rotate the prompt's actions onto a new board.

    The episode is truncated after ``max_episode_steps`` and terminated early once the cursor has stayed within
    ``still_radius`` px of where it was ``still_window`` steps earlier, for all of those steps.

    ``reset(options=...)`` accepts ``board_angle`` (radians, counter-clockwise), ``cursor`` (x, y) and a
    ``target``: a :class:`Drawing` or a list of upright canvas polylines (e.g. a prompt demonstration's ink).
    With a target, ``info["chamfer"]`` holds the Chamfer score of the ink so far and ``info["best_chamfer"]``
    the best over the episode, and the reward is the negative score. With ``score_every_step=False`` (evaluation,
    which reads the scores once), they are computed only at the step that ends the episode, the best of all steps
    included, and earlier steps give a reward of 0 and no scores.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": physics.CONTROL_HZ}

    def __init__(
        self,
        image_size: int | None = 96,
        max_episode_steps: int = MAX_EPISODE_STEPS,
        early_stop: bool = True,
        still_window: int = STILL_WINDOW,
        still_radius: float = STILL_RADIUS,
        render_mode: str | None = None,
        render_size: int = CANVAS_SIZE,
        action_frame: str = "canvas",
        cameras: tuple[str, ...] = ("image",),
        score_every_step: bool = True,
    ):
        if action_frame not in ("canvas", "board"):
            raise ValueError(f"action_frame must be 'canvas' or 'board', got {action_frame!r}")
        unknown = set(cameras) - set(CAMERAS)
        if unknown:
            raise ValueError(f"unknown cameras {sorted(unknown)}; DrawAnything's are {CAMERAS}")
        self.cameras = tuple(cameras) if image_size is not None else ()
        self.action_frame = action_frame
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.image_size = image_size
        self.max_episode_steps = max_episode_steps
        self.early_stop = early_stop
        self.still_window = still_window
        self.still_radius = still_radius
        self.render_mode = render_mode
        self.render_size = render_size
        self.score_every_step = score_every_step
        obs = {
            "agent_pos": spaces.Box(0.0, float(CANVAS_SIZE), (2,), np.float32),
            "pen_down": spaces.Box(0.0, 1.0, (1,), np.float32),
            "board_pose": spaces.Box(-1.0, 1.0, (2,), np.float32),
            "cursor_on_board": spaces.Box(-2.0, 3.0, (2,), np.float32),
            "ink_length": spaces.Box(0.0, 1000.0, (1,), np.float32),  # far above any episode's ink
        }
        for camera in self.cameras:
            obs[camera] = spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        self.observation_space = spaces.Dict(obs)
        if action_frame == "canvas":
            low, high = np.zeros(3, np.float32), np.array([CANVAS_SIZE, CANVAS_SIZE, 1.0], np.float32)
        else:  # the whole canvas at any board angle lies within [-0.6, 1.6] in board units
            low, high = np.array([-0.6, -0.6, 0.0], np.float32), np.array([1.6, 1.6, 1.0], np.float32)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        self.state = physics.initial_state(np.array(BOARD_CENTER))
        self.board_angle = 0.0

    # ---------------------------------------------------------------- episode
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"board_angle", "cursor", "target"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; expected board_angle, cursor, target")
        angle = options.get("board_angle")
        self.board_angle = (
            float(self.np_random.uniform(-MAX_BOARD_ANGLE, MAX_BOARD_ANGLE)) if angle is None else float(angle)
        )
        cursor = options.get("cursor")
        if cursor is None:
            cursor = self.np_random.uniform(*CURSOR_START_RANGE, size=2)
        self.state = physics.initial_state(np.asarray(cursor, dtype=np.float64))
        self.steps = 0
        self.positions = [self.state[:2].copy()]
        self.ink_px = 0.0
        self.paths: list[np.ndarray] = []  # canvas polylines inked so far, one per pen-down step
        # One renderer per camera: the canvas as seen, and the board's upright view (angle 0, points turned upright).
        self.renderers = {
            camera: SceneRenderer(self.image_size, self.board_angle if camera == "image" else 0.0)
            for camera in self.cameras
        }
        self._video = None if self.render_mode is None else SceneRenderer(self.render_size, self.board_angle)
        self._set_target(options.get("target"))
        return self._observation(), self._info()

    def _set_target(self, target) -> None:
        self.target_mask = None
        self.tracker = None
        self.target_overlay = None
        self.best_chamfer = float("inf")
        self.chamfer = float("inf")
        if target is None:
            return
        if isinstance(target, Drawing):
            paths = [unit_to_canvas(s, 0.0) for s in target.strokes]
        else:
            paths = [np.asarray(p, dtype=np.float64) for p in target]
        self.target_paths = paths
        self.target_mask = ink_mask(paths)
        self.tracker = ChamferTracker(self.target_mask)
        self.rollout_ink = InkMask()
        self._set_score(self.tracker.score())

    def _set_score(self, score: float) -> None:
        self.chamfer = score
        self.best_chamfer = min(self.best_chamfer, score)

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (3,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be 3 finite numbers [x, y, pen], got {action!r}")
        if self.action_frame == "board":
            action = action_to_canvas(action, self.board_angle)
        self.state, path = physics.control_step(self.state, action)
        self.steps += 1
        self.positions.append(self.state[:2].copy())
        if self.state[4] > 0.5:
            self.ink_px += float(np.linalg.norm(self.positions[-1] - self.positions[-2]))
            self.paths.append(path)
            for camera, renderer in self.renderers.items():
                renderer.add_ink(self._seen_by(camera, path))
            if self._video is not None:
                self._video.add_ink(path)
            if self.tracker is not None:
                painted = self.rollout_ink.paint(canvas_to_upright(path, self.board_angle))
                if painted is not None:
                    region, inked = painted
                    self.tracker.book(inked, region)
        terminated = self.early_stop and self._is_still()
        truncated = self.steps >= self.max_episode_steps
        scored = self.tracker is not None and (self.score_every_step or terminated or truncated)
        if scored:
            if self.score_every_step:
                self._set_score(self.tracker.score())
            else:
                self.chamfer, self.best_chamfer = self.tracker.score(), self.tracker.best()
        reward = -self.chamfer if scored else 0.0
        return self._observation(), reward, terminated, truncated, self._info(scored)

    def _is_still(self) -> bool:
        if len(self.positions) <= self.still_window:
            return False
        recent = np.asarray(self.positions[-self.still_window - 1 :])
        return bool(np.all(np.linalg.norm(recent - recent[0], axis=1) < self.still_radius))

    # ---------------------------------------------------------------- views
    def _observation(self) -> dict[str, np.ndarray]:
        obs = {
            "agent_pos": self.state[:2].astype(np.float32),
            "pen_down": np.array([self.state[4]], dtype=np.float32),
            "board_pose": board_pose(self.board_angle),
            "cursor_on_board": canvas_to_unit(self.state[:2], self.board_angle).astype(np.float32),
            "ink_length": np.array([self.ink_px / BOARD_SIZE], dtype=np.float32),
        }
        for camera, renderer in self.renderers.items():
            obs[camera] = renderer.frame(self._seen_by(camera, self.state[:2]))
        return obs

    def _seen_by(self, camera: str, points: np.ndarray) -> np.ndarray:
        """Canvas points as `camera` draws them: as they are for the canvas camera, turned upright for the board's."""
        return points if camera == "image" else upright_points(points, self.board_angle)

    def _info(self, scored: bool = True) -> dict[str, Any]:
        info: dict[str, Any] = {"state": self.state.copy(), "board_angle": self.board_angle, "steps": self.steps}
        if self.target_mask is not None and scored:
            info["chamfer"] = self.chamfer
            info["best_chamfer"] = self.best_chamfer
        return info

    def render(self):
        """An RGB frame at ``render_size`` with the target (if any) overlaid in faint red."""
        if self._video is None:
            return None
        frame = self._video.frame(self.state[:2])
        if self.target_mask is not None:
            if self.target_overlay is None:
                self.target_overlay = 0.35 * target_coverage(self.target_paths, self.board_angle, self.render_size)
            c = self.target_overlay[..., None]
            frame = np.rint(frame * (1.0 - c) + c * np.asarray(TARGET_RGB)).astype(np.uint8)
        return frame
