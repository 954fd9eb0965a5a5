"""DrawAnything's own commands: ``bpp draw sheet|video|rollout|studio`` (``bpp draw generate`` is generic; the main
job, ``bpp demo``, is a named whole run of :mod:`bpp.runs`). What loads torch is imported when a command runs:
``bpp --help`` lists this table without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.sheets import write_contact_sheet
from bpp.benchmarks.draw.studio.command import StudioCommand, studio
from bpp.benchmarks.draw.viz import episode_frames
from bpp.core.prompting import run_prompted
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.media import contact_sheet, save_animation
from bpp.utils import check_fields


@dataclass(frozen=True)
class DrawSheet:
    """Write a contact sheet PNG of a store's tasks (upright, strokes coloured by order) and demonstrations."""

    store: tyro.conf.Positional[Path]
    out: Path = Path("sheet.png")
    tasks: int = 8
    """How many tasks (rows) to show, evenly spread over the store."""
    demos: int = 5
    """Demonstrations per task to show beside the task."""
    size: int = 160

    def __post_init__(self):
        check_fields(
            self,
            ("tasks", 1 <= self.tasks <= 200, "in [1, 200]"),
            ("demos", 1 <= self.demos <= 50, "in [1, 50]"),
            ("size", 16 <= self.size <= 1024, "in [16, 1024] px"),
        )


def draw_sheet(args: DrawSheet) -> None:
    print(f"wrote {write_contact_sheet(args.store, args.out, args.tasks, args.demos, args.size)}")


@dataclass(frozen=True)
class DrawVideo:
    """Animate one stored demonstration as a GIF (or MP4 if --out ends in .mp4)."""

    store: tyro.conf.Positional[Path]
    episode: int = 0
    out: Path = Path("demo.gif")
    size: int = 256

    def __post_init__(self):
        check_fields(
            self,
            ("episode", self.episode >= 0, ">= 0"),
            ("out", self.out.suffix.lower() in (".gif", ".mp4"), "a .gif or .mp4 file"),
            ("size", 16 <= self.size <= 1024, "in [16, 1024] px"),
        )


def draw_video(args: DrawVideo) -> None:
    store = EpisodeStore(args.store)
    ep = store.episode(args.episode, ("state", "action"))
    angle = float(store.column("board_angle")[args.episode])
    frames = episode_frames(ep["state"], ep["action"].astype("float64"), angle, args.size)
    print(f"wrote {save_animation(frames, args.out)} ({len(frames)} frames)")


@dataclass(frozen=True)
class DrawRollout:
    """Prompt a trained policy with one stored demonstration and let it draw at another board angle.

    Writes a picture (prompt | rollout with the target overlaid) and an animation, and prints the Chamfer score.
    """

    checkpoint: tyro.conf.Positional[Path]
    """A run directory or checkpoint folder."""
    store: Path = Path("data/draw/human.zarr")
    """Where the prompt demonstration comes from."""
    episode: int = 0
    """The prompt: an episode of the store."""
    board_angle_deg: float = 20.0
    seed: int = 0
    out: Path = Path("outputs/rollout")

    def __post_init__(self):
        check_fields(
            self,
            ("episode", self.episode >= 0, ">= 0"),
            ("board_angle_deg", -180.0 <= self.board_angle_deg <= 180.0, "in [-180, 180]"),
            ("seed", self.seed >= 0, ">= 0"),
        )


def draw_rollout(args: DrawRollout) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.checkpoint import Checkpoint
    from bpp.policies.agent import PolicyAgent

    store = EpisodeStore(args.store)
    store.episode_slice(args.episode)  # an IndexError naming the store's episode count if out of range
    checkpoint = Checkpoint.load(args.checkpoint, use_ema=True)
    if checkpoint.benchmark != BENCHMARK.name:
        raise UserError(f"{checkpoint.path} was trained on {checkpoint.benchmark}, not {BENCHMARK.name}")
    agent = PolicyAgent(checkpoint.build_model(), record_attention=True)
    plan = [
        {
            "target_episode": args.episode,
            "prompt_episode": args.episode,
            "board_angle": float(np.radians(args.board_angle_deg)),
            "seed": args.seed,
        }
    ]
    (result,), _ = run_prompted(agent, BENCHMARK, store, plan, BENCHMARK.max_steps, [True])
    args.out.mkdir(parents=True, exist_ok=True)
    sheet = contact_sheet(
        [BENCHMARK.prompt_picture(store, args.episode), result.frames[-1]],
        ["prompt", f"rollout: Chamfer {result.score:.2f}"],
        args.out / "rollout.png",
        columns=2,
    )
    gif = save_animation(result.frames, args.out / "rollout.gif")
    final = result.extra["final_chamfer"]
    print(f"best Chamfer {result.score:.2f} px (final {final:.2f}) in {result.steps} steps")
    print(f"wrote {sheet} and {gif}")


COMMANDS = {
    "sheet": (DrawSheet, draw_sheet),
    "video": (DrawVideo, draw_video),
    "rollout": (DrawRollout, draw_rollout),
    "studio": (StudioCommand, studio),
}
"""``bpp draw <name>``; ``studio`` is also ``bpp studio``."""
