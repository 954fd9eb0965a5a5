"""Drawings recorded with an iPhUMI phone as DrawAnything-Real demonstrations (``bpp draw3d from-iphumi``).

The paper trains its real drawing policy on a person's iPhUMI demonstrations beside the scripted arm's, and prompts it
with a person's iPhUMI recording. A phone and an arm share no base frame, but both measure the canvas: ``bpp iphumi
process --canvas`` writes the pen's pose in the frame of the canvas the phone photographed, as the arm's
demonstrations write it in the frame of the canvas its scene camera photographed. So a processed recording becomes
an episode of this benchmark's store with the keys of the arm's:

* ``tip_in_canvas`` (9) is the phone's; ``pen_down`` (1) where the tip is within the pen's reach of the canvas, as
  the simulator inks; ``ink_length`` (1) the length of the ink drawn before each step;
* ``target_in_canvas`` (10) is the next step's pose, pressed ``press`` past the surface where the pen is down (the
  arm's demonstrator commands the same press), and a zero gripper command; ``action`` (10) the relative step to the
  next pose and a zero gripper command;
* ``tip_pose`` and ``canvas_pose`` are the phone's, in the frame of its pose at the episode's start: not a robot's
  base frame, so a policy that mixes phone and arm demonstrations observes with the ``canvas`` preset;
* the steps before the pen first comes within ``start_height`` of the canvas (the phone held up to look at it) are
  left out; the arm's demonstrations start at most 14 cm away.

A task's drawing (what rollouts prompted with it are scored against) is the ink of its first episode: a person's
recording has no other. Each episode's Goal-Image goal is the scene camera's photo of that ink on a canvas at a
random placement on the simulated board (:data:`~bpp.benchmarks.draw3d.dataset.GOAL_KEY`).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.draw3d.dataset import ASIDE, BENCHMARK, GOAL_KEY, random_placement
from bpp.benchmarks.draw3d.demonstrator import ScriptConfig, ink_chamfer
from bpp.benchmarks.draw3d.scene import CONTROL_HZ, PEN_REACH, Scene, canvas_transform
from bpp.core.poses import relative_actions, vector_to_pose
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.drawing.drawing import Drawing, strokes_array
from bpp.drawing.marked_canvas import CANVAS_SIDE, canvas_to_drawing
from bpp.errors import UserError

START_HEIGHT = 0.15
"""Steps before the pen first comes this close to the canvas (m) are left out."""
NEEDED = ("pose", "tip_in_canvas", "canvas_pose")


def strokes_where(points: np.ndarray, down: np.ndarray) -> list[np.ndarray]:
    """The polylines of `points` (T, 2) over each run of steps where `down` (T,) holds (runs of one point left out)."""
    runs = np.split(np.arange(len(points)), np.flatnonzero(np.diff(np.asarray(down, dtype=np.int8))) + 1)
    return [points[run] for run in runs if len(run) > 1 and down[run[0]]]


def ink_of(tip_in_canvas: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """(T, 9) pen poses in the canvas frame -> (pen down per step (T,) bool, the ink: polylines (N, 2) in metres)."""
    tip = np.asarray(tip_in_canvas, dtype=np.float64)
    down = (tip[:, 2] <= PEN_REACH) & np.all(np.abs(tip[:, :2]) <= CANVAS_SIDE / 2, axis=1)
    return down, strokes_where(tip[:, :2], down)


def episode_steps(
    source: dict[str, np.ndarray], press: float, start_height: float = START_HEIGHT
) -> tuple[dict, list[np.ndarray]]:
    """One processed iPhUMI episode's steps -> (the steps of a DrawAnything-Real episode (see the module), its ink)."""
    near = np.flatnonzero(source["tip_in_canvas"][:, 2] <= start_height)
    if not len(near):
        raise UserError(f"the pen never comes within {start_height} m of the canvas")
    kept = {key: np.asarray(value)[near[0] :] for key, value in source.items()}
    tip = kept["tip_in_canvas"].astype(np.float64)
    down, ink = ink_of(tip)
    segment = np.linalg.norm(np.diff(tip[:, :3], axis=0), axis=1) * (down[1:] & down[:-1])
    target = np.concatenate([tip[1:], tip[-1:]])
    target[:, 2] -= press * np.concatenate([down[1:], down[-1:]])
    zero = np.zeros((len(tip), 1))
    steps = {
        "tip_pose": kept["pose"].astype(np.float32),
        "tip_in_canvas": tip.astype(np.float32),
        "target_in_canvas": np.concatenate([target, zero], axis=1).astype(np.float32),
        "canvas_pose": kept["canvas_pose"].astype(np.float32),
        "ink_length": np.concatenate([[0.0], np.cumsum(segment)])[:, None].astype(np.float32),
        "pen_down": down[:, None].astype(np.float32),
        "action": np.concatenate([relative_actions(vector_to_pose(tip)), zero], axis=1).astype(np.float32),
    }
    return steps, ink


def drawing_of(task_id: str, ink: list[np.ndarray]) -> Drawing:
    """The ink (canvas-frame polylines, metres) as a drawing in DrawAnything's unit square."""
    if not ink:
        raise UserError(f"task {task_id!r}: its first episode leaves no ink on the canvas")
    return Drawing.from_strokes(task_id, [np.clip(canvas_to_drawing(s), 0.0, 1.0) for s in ink], source="iphumi")


def goal_photo(scene: Scene, ink: list[np.ndarray], placement: dict, size: int) -> np.ndarray:
    """The scene camera's photo (size, size, 3) of `ink` on a canvas at `placement`, the arm swung aside."""
    scene.reset(canvas_transform(placement["u"], placement["v"], placement["angle"]), ASIDE)
    scene.paint(ink)
    return scene.render("scene", size)


def recorded_order(store: EpisodeStore) -> list[int]:
    """The episodes of a processed iPhUMI store in the order they were recorded (its demonstrations' names begin with
    their start time; a demonstration's segments by their start)."""
    names, starts = store.config["demonstrations"], store.column("start_s")[:]
    return sorted(range(store.num_episodes), key=lambda e: (names[e], float(starts[e])))


def from_iphumi(
    source: str | Path,
    out: str | Path,
    *,
    goal_size: int = 64,
    start_height: float = START_HEIGHT,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> EpisodeStore:
    """Every episode of the processed iPhUMI store `source` (``bpp iphumi process --canvas --fps 20``) as a
    DrawAnything-Real episode in the store `out` (atomically), in the order they were recorded, so that the tasks are
    in the order of their first recording."""
    store = EpisodeStore(source)
    missing = [key for key in NEEDED if key not in store.keys]
    if missing or not store.config.get("settings", {}).get("canvas"):
        raise UserError(f"{store.path}: not processed with --canvas (it lacks {', '.join(missing) or 'the setting'})")
    if abs(float(store.config.get("fps", 0)) - CONTROL_HZ) > 1e-9:
        raise UserError(f"{store.path}: processed at {store.config.get('fps')} Hz; the arm acts at {CONTROL_HZ:g} Hz "
                        f"(bpp iphumi process --fps {CONTROL_HZ:g})")  # fmt: skip
    rng, press = np.random.default_rng(seed), ScriptConfig().press
    config = {"source": "iphumi", "iphumi_store": str(store.path), "cameras": [], "goal_size": goal_size, "seed": seed}
    tasks: dict[int, tuple[int, Drawing]] = {}
    with (
        contextlib.closing(Scene()) if goal_size else contextlib.nullcontext() as scene,
        EpisodeWriter(out, benchmark=BENCHMARK, config=config, overwrite=overwrite) as writer,
    ):
        bar = tqdm(recorded_order(store), desc=f"converting {Path(source).name}", unit="episode", disable=not progress)
        for episode in bar:
            try:
                steps, ink = episode_steps(store.episode(episode, list(NEEDED)), press, start_height)
            except UserError as err:
                raise UserError(f"{store.path}, episode {episode}: {err}") from None
            task = int(store.column("task_index")[episode])
            if task not in tasks:
                name = store.tasks[task]["id"]
                drawing = drawing_of(name, ink)
                info = {"source": "iphumi", "num_strokes": len(drawing.strokes)}
                tasks[task] = (writer.add_task(name, info, strokes=strokes_array(drawing)), drawing)
            index, drawing = tasks[task]
            placement = random_placement(rng)
            columns = {f"canvas_{k}": v for k, v in placement.items()} | {"chamfer": ink_chamfer(ink, drawing.strokes)}
            if scene is not None:
                columns[GOAL_KEY] = goal_photo(scene, ink, placement, goal_size)
            writer.add_episode(steps, index, **columns)
        return writer.close()
