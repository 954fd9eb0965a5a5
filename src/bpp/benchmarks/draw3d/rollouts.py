"""DrawAnything-Real's evaluation: a policy drawing on the simulated arm, rollouts in lockstep.

Each rollout places the canvas at a new random placement, measures its pose from the scene camera's photo (the
policy observes the measured pose, or observes and acts in its frame, as a lab's would), moves the pen unrecorded to
a random start in front of the canvas, then lets the policy act for ``max_steps`` control steps. The score is
DrawAnything's Chamfer distance between the ink on the canvas and the task's drawing
(:func:`bpp.benchmarks.draw3d.demonstrator.ink_chamfer`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from PIL import Image

from bpp.benchmarks.draw3d.dataset import measure_canvas
from bpp.benchmarks.draw3d.demonstrator import ScriptConfig, execute_approach, ink_chamfer, random_pose
from bpp.benchmarks.draw3d.photo import photograph_canvas, rectified_chamfer
from bpp.benchmarks.draw3d.scene import HOME_QPOS, Scene, canvas_transform
from bpp.core.contract import RolloutResult, frames_to_record
from bpp.core.poses import invert, pose_to_vector, vector_to_pose
from bpp.data.store import EpisodeStore
from bpp.drawing.drawing import task_drawing
from bpp.drawing.marked_canvas import CanvasNotFound, pose_error
from bpp.errors import UserError

ACTION_KEYS = ("action", "target_in_canvas")
"""The action keys a draw3d policy may act with: relative pen steps, or pen poses in the measured canvas's frame."""
FRAME_EVERY = 10
"""A recorded rollout keeps one scene-camera frame every this many steps (and the last), then the canvas as the photo
that scored it shows it, rectified upright (when the photo gave the canvas pose)."""
FRAME_SIZE = 256

_SCENES: list = []


def _scenes(count: int, image_size: int) -> list:
    """`count` scenes of this process, built once and reused across batches."""
    while len(_SCENES) < count:
        _SCENES.append(Scene(image_size=image_size))
    for scene in _SCENES[:count]:
        scene.image_size = image_size
    return _SCENES[:count]


@dataclass(frozen=True)
class _Canvas:
    """A rollout's canvas as measured from its photo (``T_base_canvas``), with what each step reads of it."""

    pose: np.ndarray
    inverse: np.ndarray
    vector: np.ndarray

    @classmethod
    def measured(cls, pose: np.ndarray) -> _Canvas:
        return cls(pose, invert(pose), pose_to_vector(pose).astype(np.float32))


def _observe(scene, canvas: _Canvas, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """The observation `keys` of `scene`, whose canvas was measured at `canvas`."""
    values = {
        "tip_pose": lambda: pose_to_vector(scene.tip_pose()).astype(np.float32),
        "tip_in_canvas": lambda: pose_to_vector(canvas.inverse @ scene.tip_pose()).astype(np.float32),
        "canvas_pose": lambda: canvas.vector,
        "ink_length": lambda: np.array([scene.ink.length], np.float32),
        "pen_down": lambda: np.array([float(scene.ink.down)], np.float32),
        "wrist": lambda: scene.render("wrist"),
    }
    return {key: values[key]() for key in keys}


def relative_step(scene, canvas: np.ndarray, action: np.ndarray, key: str) -> np.ndarray:
    """The scene's action (the commanded pose's step) for a policy's `action` of kind `key`: ``action`` is that
    step already; ``target_in_canvas`` is the commanded pose to go to, in the frame of the measured `canvas`."""
    if key == "action":
        return action
    if key not in ACTION_KEYS:
        raise ValueError(f"draw3d executes actions of key {' or '.join(ACTION_KEYS)}, not {key!r}")
    target = canvas @ vector_to_pose(action[:9])
    return np.append(pose_to_vector(invert(scene.target) @ target), action[9:])


def _from_photo(scene, strokes) -> tuple[dict, np.ndarray | None]:
    """The score a lab would measure (:func:`bpp.benchmarks.draw3d.photo.photograph_canvas`), once the rollout is
    over, and the rectified photo it was measured from; ``chamfer_from_photo`` is absent, and the photo None, when the
    photo does not give the canvas pose."""
    try:
        rectified = photograph_canvas(scene)
    except CanvasNotFound:
        return {"photo_found_canvas": 0.0}, None
    return {"chamfer_from_photo": float(rectified_chamfer(rectified, strokes)), "photo_found_canvas": 1.0}, rectified


def run_rollouts(
    agent, store: EpisodeStore, rollouts: Sequence[Mapping], max_steps: int, record_frames: Sequence[bool | str]
) -> list[RolloutResult]:
    """See :meth:`bpp.core.contract.Benchmark.run_rollouts`."""

    spec = agent.data_spec
    if spec.action_key not in ACTION_KEYS:
        raise UserError(f"draw3d executes actions of key {' or '.join(ACTION_KEYS)}, not {spec.action_key!r}")
    keys = list(agent.obs_keys)
    scenes = _scenes(len(rollouts), spec.image_size)
    drawings, canvases, extras = [], [], []
    for scene, rollout in zip(scenes, rollouts, strict=True):
        rng = np.random.default_rng(int(rollout["seed"]))
        truth = canvas_transform(rollout["canvas_u"], rollout["canvas_v"], rollout["canvas_angle"])
        try:
            measured, from_photo = measure_canvas(scene, truth), True
        except CanvasNotFound:
            measured, from_photo = truth, False  # a lab would move the arm and photograph again
        scene.reset(truth, HOME_QPOS)
        execute_approach(scene, measured @ random_pose(rng, ScriptConfig()))
        scene.ink.strokes.clear()
        scene.ink.down = False
        task = int(store.column("task_index")[int(rollout["target_episode"])])
        drawings.append(task_drawing(store, task))
        canvases.append(_Canvas.measured(measured))
        extras.append({"canvas_from_photo": from_photo, "canvas_pose_error_mm": pose_error(measured, truth)[0] * 1e3})
    record = [frames_to_record(r) for r in record_frames]
    frames: list[list] = [[] for _ in rollouts]
    for t in range(max_steps):
        observed = [_observe(scene, canvas, keys) for scene, canvas in zip(scenes, canvases, strict=True)]
        actions = np.asarray(agent.act_batch({k: np.stack([o[k] for o in observed]) for k in keys}), np.float64)
        for i, scene in enumerate(scenes):
            if record[i] == "all" and t % FRAME_EVERY == 0:
                frames[i].append(scene.render("scene", FRAME_SIZE))
            scene.step(relative_step(scene, canvases[i].pose, actions[i], spec.action_key))
    results = []
    for i, scene in enumerate(scenes):
        if record[i]:
            frames[i].append(scene.render("scene", FRAME_SIZE))
        score = ink_chamfer(scene.ink.polylines(), drawings[i].strokes)
        from_photo, rectified = _from_photo(scene, drawings[i].strokes)
        if record[i] and rectified is not None:
            # the last frame: the canvas as photographed for the score, upright like the prompt's picture
            canvas = np.asarray(Image.fromarray(rectified).resize((FRAME_SIZE, FRAME_SIZE), Image.BILINEAR))
            frames[i] = [*frames[i], canvas] if record[i] == "all" else [canvas]
        extra = {**extras[i], "ink_length_m": round(scene.ink.length, 4), **from_photo}
        results.append(RolloutResult(score=float(score), steps=max_steps, extra=extra, frames=frames[i]))
    return results
