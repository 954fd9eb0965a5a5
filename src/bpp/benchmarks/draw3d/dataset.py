"""DrawAnything-Real's demonstrations: drawings demonstrated by the scripted demonstrator on the simulated arm, each on
its own random canvas placement, into an episode store (``bpp draw3d generate``).

Per demonstration: the canvas is placed at random on the board; its pose is measured from the scene camera's photo
(the arm swung aside, out of view), as a lab measures it; the demonstrator plans in that measured frame and the arm
executes the plan. A demonstration whose photo gives no pose (a marker unclear) or whose ink is too far from the
drawing is counted as a failure and not stored; the task is demonstrated again with the next placement.

Per step: ``tip_pose`` (9: the pen tip's pose in the robot's base frame, position and 6-D rotation), ``canvas_pose``
(9: the measured canvas pose, constant over the episode), ``tip_in_canvas`` (9: the pen tip's pose in the measured
canvas's frame), ``ink_length`` (1, m) and ``pen_down`` (1), optionally ``wrist`` (the wrist camera); ``action`` (10:
the relative pen step and a zero gripper command) and ``target_in_canvas`` (10: the same step as the commanded pen pose
it leads to, in the measured canvas's frame, and the gripper command).
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.draw3d.demonstrator import ScriptConfig, execute, ink_chamfer, plan_drawing
from bpp.benchmarks.draw3d.scene import BOARD, CONTROL_HZ, HOME_QPOS, Scene, canvas_transform
from bpp.core.poses import pose_to_vector
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.drawing.drawing import strokes_array
from bpp.drawing.files import load_drawings
from bpp.drawing.human import human_drawings
from bpp.drawing.marked_canvas import CanvasNotFound, canvas_in_base, canvas_pose
from bpp.drawing.procedural import ProceduralConfig, generate_drawing, procedural_id
from bpp.errors import UserError
from bpp.executor import Executor, as_executor
from bpp.utils import check_fields

BENCHMARK = "draw3d"
CAMERAS = ("wrist",)
ASIDE = np.array([1.6, -1.2, 0.0, -2.9, 0.0, 2.2, 0.78])
"""The arm folded and swung to the side whenever the board is photographed: out of the scene camera's view, its shadow
off the board (folded straight back, its shadow fell on the canvas and made markers look partly hidden)."""
PLACEMENT = {"u": (-0.25, 0.25), "v": (-0.08, 0.08), "angle": (-45.0, 45.0)}
"""Where a canvas goes on the board: metres right and up its slope from its centre, and degrees about its normal."""
PHOTO_SIZE = 640
"""The scene camera's photo for the canvas pose (px, square)."""
GOAL_KEY = "goal_scene"
"""Per-episode column: the scene camera's photo of the board once the demonstration is done (the arm swung aside),
the Goal-Image baseline's goal (camera ``scene``, the final frame)."""


@dataclass(frozen=True)
class Draw3DConfig:
    """What ``bpp draw3d generate`` makes."""

    num_tasks: int = 200
    demos_per_task: int = 5
    source: str = "procedural"
    """procedural (DrawAnything's generator), human (DrawAnything's human-made drawings) or files (--drawings)."""
    drawings: tuple[Path, ...] = ()
    procedural: ProceduralConfig = ProceduralConfig()
    script: ScriptConfig = ScriptConfig()
    cameras: tuple[str, ...] = ()
    """Cameras rendered per step (wrist; none for the state-only preset)."""
    image_size: int = 96
    goal_size: int = 64
    """Side (px) of each demonstration's final photo of the board (:data:`GOAL_KEY`; 0: none), the Goal-Image
    baseline's goal."""
    max_chamfer: float = 3.0
    """A demonstration whose ink is farther than this from its drawing (DrawAnything px) fails and is not stored."""
    max_tries_factor: int = 3
    """A task gets at most this many times its demonstrations in tries."""
    seed: int = 0

    def __post_init__(self):
        check_fields(
            self,
            ("num_tasks", self.num_tasks >= 1, ">= 1"),
            ("demos_per_task", self.demos_per_task >= 1, ">= 1"),
            ("source", self.source in ("procedural", "human", "files"), "procedural, human or files"),
            ("cameras", set(self.cameras) <= set(CAMERAS), f"some of {', '.join(CAMERAS)}"),
            ("image_size", 8 <= self.image_size <= 512, "in [8, 512] px"),
            ("goal_size", self.goal_size == 0 or 8 <= self.goal_size <= 512, "0 or in [8, 512] px"),
            ("max_chamfer", self.max_chamfer > 0, "> 0 px"),
            ("max_tries_factor", self.max_tries_factor >= 1, ">= 1"),
        )


PRESETS = {
    "debug": Draw3DConfig(num_tasks=4, demos_per_task=2, procedural=ProceduralConfig(max_parts=2)),
    "cpu": Draw3DConfig(num_tasks=200, demos_per_task=5),
    "paper": Draw3DConfig(num_tasks=800, demos_per_task=6, cameras=("wrist",)),
    "paper-human": Draw3DConfig(demos_per_task=5, source="files", cameras=("wrist",)),
}
"""``paper`` and ``paper-human`` are the two parts of the paper's training mixture, merged with ``bpp store merge``:
800 procedural tasks x 6 demonstrations, and human-made drawings x 5 (the paper's 200; here your drawing files,
``--drawings``, demonstrated by the scripted arm)."""
"""``debug`` for tests; ``cpu`` state-only, for a CPU; ``paper`` the paper's 800 scripted tasks x 6 with the wrist
camera (its 200 human iPhUMI tasks x 5 come from recordings: ``bpp iphumi process``)."""


def random_placement(rng: np.random.Generator) -> dict:
    return {key: float(rng.uniform(*bounds)) for key, bounds in PLACEMENT.items()}


_SCENE = None


def _scene(image_size: int):
    """The process's scene, built once (a second of MuJoCo compilation)."""
    global _SCENE

    if _SCENE is None or _SCENE.image_size != image_size:
        _SCENE = Scene(image_size=image_size)
    return _SCENE


def measure_canvas(scene, truth: np.ndarray) -> np.ndarray:
    """Place the canvas at `truth` with the arm swung aside, photograph it with the scene camera and return the
    canvas pose the photo gives in the base frame (:class:`bpp.drawing.marked_canvas.CanvasNotFound` if none)."""
    scene.reset(truth, ASIDE)
    camera = scene.camera_pose("scene")
    photo = scene.render("scene", PHOTO_SIZE)
    found = canvas_pose(photo, scene.camera_intrinsics("scene", PHOTO_SIZE), up=camera[:3, :3].T @ BOARD[:, 1])
    return canvas_in_base(camera, found)


def demonstrate_task(job: tuple) -> tuple[list, dict]:
    """Worker: one task's demonstrations -> ([(steps, columns)], counts). A pure function of the job."""
    drawing, seed_seq, cfg = job
    rng = np.random.default_rng(seed_seq)
    scene = _scene(cfg.image_size)
    episodes, counts = [], {"tries": 0, "no_canvas_pose": 0, "too_far": 0}
    while len(episodes) < cfg.demos_per_task and counts["tries"] < cfg.max_tries_factor * cfg.demos_per_task:
        counts["tries"] += 1
        placement = random_placement(rng)
        truth = canvas_transform(placement["u"], placement["v"], placement["angle"])
        try:
            measured = measure_canvas(scene, truth)
        except CanvasNotFound:
            counts["no_canvas_pose"] += 1
            continue
        scene.reset(truth, HOME_QPOS)
        plan = plan_drawing(drawing.strokes, rng, cfg.script, CONTROL_HZ)
        recorded = execute(scene, measured, plan, cameras=cfg.cameras)
        score = ink_chamfer(recorded.strokes, drawing.strokes)
        if score > cfg.max_chamfer:
            counts["too_far"] += 1
            continue
        n = len(recorded.actions)
        steps = {
            "tip_pose": recorded.tip,
            "tip_in_canvas": recorded.tip_in_canvas,
            "target_in_canvas": np.concatenate([recorded.targets_in_canvas, np.zeros((n, 1), np.float32)], axis=1),
            "canvas_pose": np.repeat(pose_to_vector(measured)[None].astype(np.float32), n, axis=0),
            "ink_length": recorded.ink_length,
            "pen_down": recorded.pen_down,
            "action": recorded.actions.astype(np.float32),
            **recorded.frames,
        }
        columns = {f"canvas_{k}": v for k, v in placement.items()} | {"chamfer": score}
        if cfg.goal_size:
            scene.fold(ASIDE)
            columns[GOAL_KEY] = scene.render("scene", cfg.goal_size)
        episodes.append((steps, columns))
    return episodes, counts


def _drawings(cfg: Draw3DConfig) -> list:
    if cfg.source == "human":
        return list(human_drawings())
    if cfg.source == "files":
        if not cfg.drawings:  # a preset of this source leaves them to the command line
            raise UserError("source files: give the drawing files (JSON or SVG) with --drawings")
        return list(load_drawings(cfg.drawings))
    seeds = np.random.SeedSequence([cfg.seed, 1]).spawn(cfg.num_tasks)
    return [generate_drawing(np.random.default_rng(s), cfg.procedural, procedural_id(cfg.seed, i))[0]
            for i, s in enumerate(seeds)]  # fmt: skip


def generate(
    cfg: Draw3DConfig, out: str | Path, workers: int | Executor = 0, overwrite: bool = False, progress: bool = True
) -> EpisodeStore:
    """Demonstrate every task of `cfg` into the store at `out` (atomically), over `workers` processes (0: all cores)
    or an :class:`~bpp.executor.Executor`."""
    drawings = _drawings(cfg)  # drawing files are validated before anything is written
    seeds = np.random.SeedSequence(cfg.seed).spawn(len(drawings))
    jobs = [(d, s, cfg) for d, s in zip(drawings, seeds, strict=True)]
    config = {**asdict(cfg), "drawings": [str(p) for p in cfg.drawings]}
    totals = {"tries": 0, "no_canvas_pose": 0, "too_far": 0}
    with EpisodeWriter(out, benchmark=BENCHMARK, config=config, overwrite=overwrite) as writer:
        # Workers stopped however it ends, Ctrl-C left to this process; spawned: MuJoCo's OpenGL does not survive fork.
        with contextlib.closing(as_executor(workers).map(demonstrate_task, jobs, ordered=True)) as results:
            bar = tqdm(results, total=len(jobs), desc=f"generating {Path(out).name}", unit="task", disable=not progress)
            for (drawing, _, _), (episodes, counts) in zip(jobs, bar, strict=True):
                for key in totals:
                    totals[key] += counts[key]
                if not episodes:
                    raise UserError(
                        f"drawing {drawing.id!r}: no demonstration succeeded in {counts['tries']} tries ({counts})"
                    )
                info = {"source": cfg.source, "num_strokes": len(drawing.strokes), **counts}
                task = writer.add_task(drawing.id, info, strokes=strokes_array(drawing))
                for steps, columns in episodes:
                    writer.add_episode(steps, task, **columns)
        store = writer.close()
    failed = totals["tries"] - store.num_episodes
    if progress:
        print(f"[draw3d] {store.num_episodes} demonstrations in {totals['tries']} tries; {failed} failed "
              f"({totals['no_canvas_pose']} without a canvas pose from the photo, {totals['too_far']} with ink over "
              f"{cfg.max_chamfer:g} px from the drawing)")  # fmt: skip
    return store
