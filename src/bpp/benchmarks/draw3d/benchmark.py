"""DrawAnything-Real on a simulated arm as a benchmark (the contract of :mod:`bpp.core.contract`).

The paper's real drawing benchmark: a square canvas with four red corner markers anywhere on a whiteboard at any
rotation within ±45 degrees, its pose measured from a photo; a 6-DoF arm drawing with a pen; the policy acting with
relative 6-DoF pen actions from the pen's pose (and a wrist camera, in the paper's setting); Chamfer against the
drawing. Here the arm and board are simulated (:mod:`bpp.benchmarks.draw3d.scene`), so a lab with an arm needs only
its driver. Drawings, the human-made set, drawing files and the Chamfer metric are DrawAnything's.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from bpp.benchmarks.draw3d.dataset import BENCHMARK as NAME
from bpp.benchmarks.draw3d.dataset import GOAL_KEY, PRESETS, Draw3DConfig, generate, random_placement
from bpp.benchmarks.draw3d.phone import strokes_where
from bpp.benchmarks.draw3d.rollouts import run_rollouts
from bpp.benchmarks.draw3d.scene import CONTROL_HZ
from bpp.core.contract import Metric, RolloutResult, TaskSet
from bpp.data.frames import stored_frames
from bpp.data.spec import ObservationPreset
from bpp.data.store import EpisodeStore, stored_or_made
from bpp.drawing.geometry import unit_to_canvas
from bpp.drawing.marked_canvas import canvas_to_drawing
from bpp.drawing.metric import ink_mask
from bpp.errors import UserError
from bpp.media import resize_frames

OBSERVATIONS: Mapping[str, ObservationPreset] = {
    "state": ObservationPreset(
        proprio_keys=("tip_pose", "pen_down"),
        lowdim_keys=("canvas_pose", "ink_length"),
        goal_camera="scene",
        description="the pen tip's pose, whether it touches, the canvas pose measured from a photo, the ink drawn so "
        "far (m); for CPUs",
    ),
    "canvas": ObservationPreset(
        proprio_keys=("tip_in_canvas", "pen_down"),
        lowdim_keys=("ink_length",),
        action_key="target_in_canvas",
        goal_camera="scene",
        description="in the frame of the canvas measured from a photo: the pen tip's pose, whether it touches, the "
        "ink drawn so far (m), and actions as the commanded pen pose in that frame (a CPU stand-in for the wrist "
        "camera's view of the canvas; the counterpart of DrawAnything-Sim's board)",
    ),
    "wrist": ObservationPreset(
        proprio_keys=("tip_pose",),
        image_keys=("wrist",),
        image_size=96,
        goal_camera="wrist",
        description="the paper's real setting: the pen tip's pose and the wrist camera at 96x96 (generate with "
        "--cameras wrist)",
    ),
}


class DrawAnythingReal:
    """DrawAnything-Real: drawings on a whiteboard canvas by a simulated 6-DoF arm."""

    name = NAME
    command = "draw3d"
    control_hz = CONTROL_HZ
    """Actions per second of its robot (a policy server tells its clients)."""
    command_table = "bpp.benchmarks.draw3d.commands:COMMANDS"
    description = (
        "DrawAnything-Real on a simulated Panda: a canvas with red corner markers anywhere on a whiteboard (±45 "
        "degrees), its pose from a photo, 6-DoF relative pen actions, DrawAnything's Chamfer on the ink"
    )
    data_config = Draw3DConfig
    data_presets = PRESETS
    default_data_dir = Path("data/draw3d")
    derived_keys: Mapping[str, tuple[str, tuple[int, ...]]] = {}
    observations = OBSERVATIONS
    metric = Metric(
        "Chamfer distance",
        unit="px",
        lower_is_better=True,
        good_threshold=5.0,
        description="DrawAnything's Chamfer distance (its 512-px canvas, the drawing's unit square its 350-px board) "
        "between the ink the pen left on the canvas and the drawing",
    )
    max_steps = 500
    """25 s at 20 Hz: the longest demonstrations of the cpu preset's drawings take about 20."""
    task_sets: Mapping[str, str] = {"human": "DrawAnything's 50 human-made drawings, 5 demonstrations each"}

    def default_observation(self, size: str) -> str:
        return "wrist" if size == "paper" else "state"

    def generate(self, cfg, out: Path, *, workers: int = 0, overwrite: bool = False, progress: bool = True):
        return generate(cfg, out, workers=workers, overwrite=overwrite, progress=progress)

    def frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """The camera frames generated with the store (resized if another size is asked for); camera ``scene`` has one
        frame per demonstration, its final photo of the board (:data:`~bpp.benchmarks.draw3d.dataset.GOAL_KEY`)."""
        if key == "scene" and last_only:
            try:
                return resize_frames(store.column(GOAL_KEY)[episode][None], size)
            except KeyError:
                raise ValueError(f"{store.path} has no final photos: generate it with --goal-size (e.g. 64)") from None
        if key not in store.keys:
            raise ValueError(f"{store.path} has no {key!r} frames: generate it with --cameras {key}")

        return stored_frames(store, episode, key, size, last_only, steps)

    # ------------------------------------------------------------ evaluation
    def task_set(self, name: str, data_dir: Path, workers: int = 0) -> TaskSet:
        if name not in self.task_sets:
            raise UserError(f"unknown task set {name!r}; DrawAnything-Real has {', '.join(self.task_sets)}")
        return self._generated(Draw3DConfig(num_tasks=50, source="human"), Path(data_dir) / "human.zarr", name, workers)

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: int = 0) -> TaskSet:
        key = hashlib.sha256("\0".join(str(Path(f).resolve()) for f in files).encode()).hexdigest()[:12]
        cfg = Draw3DConfig(source="files", drawings=tuple(Path(f) for f in files), demos_per_task=2)
        return self._generated(cfg, Path(data_dir) / f"files-{key}.zarr", "your drawings", workers)

    def _generated(self, cfg: Draw3DConfig, path: Path, label: str, workers: int) -> TaskSet:
        store = stored_or_made(path, lambda path: self.generate(cfg, path, workers=workers, overwrite=True), cfg)
        return TaskSet(store, label)

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        return {f"canvas_{k}": v for k, v in random_placement(rng).items()}

    def run_rollouts(self, agent, store, rollouts, max_steps, record_frames) -> list[RolloutResult]:
        return run_rollouts(agent, store, rollouts, max_steps, record_frames)

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        """The demonstration's ink on the canvas (from its pen poses in the canvas's frame where the pen touched),
        upright: an arm's demonstration or a phone's (``bpp draw3d from-iphumi``)."""
        data = store.episode(episode, ["tip_in_canvas", "pen_down"])
        strokes = strokes_where(data["tip_in_canvas"][:, :2].astype(np.float64), data["pen_down"][:, 0] > 0.5)
        mask = ink_mask([unit_to_canvas(canvas_to_drawing(s), 0.0) for s in strokes])
        picture = np.where(mask[..., None], np.uint8(20), np.uint8(245)).repeat(3, axis=2)

        return np.asarray(Image.fromarray(picture).resize((size, size), Image.BILINEAR))

    def describe_rollout(self, row: Mapping) -> str:
        return f"canvas {row.get('canvas_angle', 0.0):+.0f}°"


BENCHMARK = DrawAnythingReal()
