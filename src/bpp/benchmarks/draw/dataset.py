"""Generate DrawAnything-Sim datasets (training tasks, the unseen human-made set, user drawings) into a store."""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.draw.demonstrator import DemoConfig, Demonstration, demonstrate, replay_paths
from bpp.benchmarks.draw.env import CURSOR_START_RANGE, action_to_board, board_pose, ink_lengths
from bpp.benchmarks.draw.render import render_frames
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.drawing.drawing import Drawing, strokes_array
from bpp.drawing.files import load_drawings
from bpp.drawing.geometry import MAX_BOARD_ANGLE, canvas_to_unit
from bpp.drawing.human import human_drawings
from bpp.drawing.procedural import ProceduralConfig, describe_parts, generate_drawing, procedural_id
from bpp.errors import UserError
from bpp.executor import Executor, as_executor
from bpp.utils import check_fields

BENCHMARK = "drawanything"


@dataclass(frozen=True)
class DrawDataConfig:
    """What to generate. ``source`` picks the drawings; the rest shapes demonstrations."""

    source: Literal["procedural", "human", "files"] = "procedural"
    """procedural: random training drawings; human: the 50 built-in unseen drawings; files: --drawings."""
    num_tasks: int = 2000
    """Number of procedural tasks (ignored for other sources)."""
    demos_per_task: int = 5
    drawings: tuple[Path, ...] = ()
    """JSON stroke files or SVG files (source=files)."""
    seed: int = 0
    describe: bool = False
    """Give each procedural task an instruction describing its parts in order ("draw a line, then draw an oval"),
    so that language-conditioned policies can train; without it, tasks have no instruction."""
    procedural: ProceduralConfig = field(default_factory=ProceduralConfig)
    demo: DemoConfig = field(default_factory=DemoConfig)

    def __post_init__(self):
        check_fields(
            self,
            ("demos_per_task", 1 <= self.demos_per_task <= 10_000, "in [1, 10000]"),
            ("num_tasks", self.source != "procedural" or 1 <= self.num_tasks <= 10_000_000, "in [1, 10000000]"),
            ("seed", self.seed >= 0, ">= 0"),
        )
        if self.source == "files" and not self.drawings:
            raise UserError("source=files needs at least one drawing file (--drawings FILE ...)")
        if self.describe and self.source != "procedural":
            raise UserError(f"describe needs procedural drawings (their list of parts), not source={self.source}")


PRESETS: dict[str, DrawDataConfig] = {
    "paper": DrawDataConfig(),
    "cpu": DrawDataConfig(num_tasks=500),
    "debug": DrawDataConfig(num_tasks=12, demos_per_task=3),
    "human": DrawDataConfig(source="human"),
    "parts-1-3": DrawDataConfig(procedural=ProceduralConfig(min_parts=1, max_parts=3)),
    "parts-4-6": DrawDataConfig(procedural=ProceduralConfig(min_parts=4, max_parts=6)),
}
"""Named configurations: ``paper`` is the paper's 2000 tasks x 5 demos; ``human`` the unseen evaluation set."""


def stratified_angles(rng: np.random.Generator, n: int) -> np.ndarray:
    """n board angles in [-45, 45] deg, one per equal slice of the range (in random order), so demos differ."""
    width = 2 * MAX_BOARD_ANGLE / n
    angles = -MAX_BOARD_ANGLE + width * (np.arange(n) + rng.uniform(0.0, 1.0, n))
    return rng.permutation(angles)


def _task_job(job: tuple) -> tuple[Drawing, dict, list[Demonstration]]:
    """Worker: one task's drawing (generated if not given) and its demonstrations. Pure function of `job`."""
    index, drawing, seed_seq, cfg = job
    rng = np.random.default_rng(seed_seq)
    info: dict = {}
    if drawing is None:
        drawing, kinds = generate_drawing(rng, cfg.procedural, procedural_id(cfg.seed, index))
        info["parts"] = kinds
    demos = []
    for angle in stratified_angles(rng, cfg.demos_per_task):
        start = rng.uniform(*CURSOR_START_RANGE, size=2)
        demos.append(demonstrate(drawing, float(angle), start, rng, cfg.demo))
    return drawing, info, demos


def episode_steps(demo: Demonstration) -> dict[str, np.ndarray]:
    """The per-step arrays stored for one demonstration."""
    n = len(demo)
    return {
        "state": demo.states.astype(np.float64),
        "action": demo.actions.astype(np.float32),
        "agent_pos": demo.states[:, 0:2].astype(np.float32),
        "pen_down": demo.states[:, 4:5].astype(np.float32),
        "board_pose": np.repeat(board_pose(demo.board_angle)[None], n, axis=0),
        "cursor_on_board": canvas_to_unit(demo.states[:, 0:2], demo.board_angle).astype(np.float32),
        "action_on_board": action_to_board(demo.actions, demo.board_angle).astype(np.float32),
        "ink_length": ink_lengths(demo.states[:, 0:2], demo.states[:, 4])[:, None].astype(np.float32),
    }


def generate(
    cfg: DrawDataConfig, out: str | Path, workers: int | Executor = 0, overwrite: bool = False, progress: bool = True
) -> EpisodeStore:
    """Generate a dataset into the store at `out`, in parallel over `workers` processes (0: all cores) or an
    :class:`~bpp.executor.Executor`."""
    if cfg.source == "procedural":
        drawings: list[Drawing | None] = [None] * cfg.num_tasks
    elif cfg.source == "human":
        drawings = list(human_drawings())
    else:
        drawings = list(load_drawings(cfg.drawings))  # validates every file before anything is written
    seeds = np.random.SeedSequence(cfg.seed).spawn(len(drawings))
    jobs = [(i, d, s, cfg) for i, (d, s) in enumerate(zip(drawings, seeds, strict=True))]
    config = {**asdict(cfg), "drawings": [str(p) for p in cfg.drawings]}
    # fork: cheap, and works from any entry point; generation never touches torch or threads.
    results = as_executor(workers).map(_task_job, jobs, ordered=True, start_method="fork", chunksize=16)
    with EpisodeWriter(out, benchmark=BENCHMARK, config=config, overwrite=overwrite) as writer:
        with contextlib.closing(results):
            bar = tqdm(results, total=len(jobs), desc=f"generating {Path(out).name}", unit="task", disable=not progress)
            for drawing, info, demos in bar:
                info = {
                    **info,
                    "source": cfg.source,
                    "num_strokes": len(drawing.strokes),
                    "ink_length": round(drawing.ink_length, 6),
                }
                instruction = describe_parts(info["parts"]) if cfg.describe else ""
                task = writer.add_task(drawing.id, info, instruction=instruction, strokes=strokes_array(drawing))
                for demo in demos:
                    writer.add_episode(episode_steps(demo), task, board_angle=demo.board_angle, speed=demo.speed)
        return writer.close()


# --------------------------------------------------------------------------- reading back
def episode_physics(store: EpisodeStore, episode: int) -> tuple[np.ndarray, np.ndarray]:
    """An episode's (T, 5) states (a view of the cached column: do not modify it) and (T, 3) float64 actions, from
    the store's whole columns, read into memory once (52 bytes a step, about 51 MB for the paper's 10,000
    demonstrations): a loader renders a few episodes per batch, and reading each from the store took longer than
    rendering it."""
    sl = store.episode_slice(episode)
    return store.array("state")[sl], store.array("action")[sl].astype(np.float64)


def episode_paths(store: EpisodeStore, episode: int) -> list[np.ndarray]:
    """Canvas polylines inked by each pen-down step of an episode, by exact replay of the stored physics."""
    return replay_paths(*episode_physics(store, episode))


def render_episode_steps(
    store: EpisodeStore, episode: int, image_size: int, steps: np.ndarray, camera: str = "image"
) -> np.ndarray:
    """(k, R, R, 3) uint8 observations of `camera` (the env's ``image`` or ``board_image``) of a stored episode at
    `steps` (any order, repeats allowed), identical to ``render_episode(...)[steps]`` but rendering only those
    frames (step T: the frame after the last step)."""
    states, actions = episode_physics(store, episode)
    angle = float(store.column("board_angle")[episode])
    return render_frames(states, actions, angle, image_size, steps, upright=camera == "board_image")


def render_last_observation(store: EpisodeStore, episode: int, image_size: int, camera: str = "image") -> np.ndarray:
    """(R, R, 3) uint8: the episode's final observation by `camera`, identical to ``render_episode(...)[-1]`` but
    rendering one frame instead of one per step (a goal image)."""
    sl = store.episode_slice(episode)
    return render_episode_steps(store, episode, image_size, [sl.stop - sl.start - 1], camera)[0]


def render_episode(store: EpisodeStore, episode: int, image_size: int, camera: str = "image") -> np.ndarray:
    """(T, R, R, 3) uint8 observations by `camera` of a stored episode, identical to what the env showed."""
    sl = store.episode_slice(episode)
    return render_episode_steps(store, episode, image_size, np.arange(sl.stop - sl.start), camera)
