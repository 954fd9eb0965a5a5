"""The LeRobot dataset commands: ``bpp lerobot import|export`` (``bpp lerobot generate`` only points to import)."""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated, Literal

import tyro

from bpp.benchmarks.lerobot.export import VCODECS, export_store
from bpp.benchmarks.lerobot.importer import ImportSettings, import_dataset, parse_episodes
from bpp.core.registry import open_store
from bpp.utils import check_fields


@dataclass(frozen=True)
class LeRobotImport(ImportSettings):
    """Import a LeRobot v3 dataset (a local folder, or a repo id LeRobot or the Hugging Face Hub already cached) into
    a store: its tasks, episodes, numeric features, cameras (decoded at --image-size) and fps. Nothing is downloaded.

    With --holdout-episodes N (the last N episodes of each task) or --holdout-tasks N (the last N tasks), those
    episodes go to a second store, STORE-heldout.zarr, for `bpp eval RUN --tasks STORE-heldout.zarr`.

    Examples:
      bpp lerobot import ~/datasets/koch_pick --out data/lerobot/koch.zarr --holdout-episodes 2
      bpp lerobot import lerobot/pusht --out data/lerobot/pusht.zarr --image-size 64 --episodes 0:100
    """

    source: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="PATH_OR_REPO_ID")] = ""
    """The dataset's folder (with meta/info.json), or a repo id (org/name) found in LeRobot's or the Hub's cache."""
    out: Path = Path("data/lerobot/imported.zarr")
    """Store to write (a .zarr folder)."""
    heldout_out: Path | None = None
    """Where the held-out store goes (default: the --out store's name + -heldout)."""
    overwrite: bool = False
    """Replace existing stores."""

    def __post_init__(self):
        super().__post_init__()
        check_fields(self, ("source", bool(self.source), "a dataset folder or a cached repo id"))


def lerobot_import(args: LeRobotImport) -> None:
    t0 = time.perf_counter()
    settings = ImportSettings(**{f.name: getattr(args, f.name) for f in fields(ImportSettings)})
    store, held = import_dataset(args.source, args.out, settings, args.heldout_out, args.overwrite)
    print(f"wrote {store}")
    if held is not None:
        print(f"wrote {held} (held out: evaluate with --tasks {held.path})")
    print(f"  {time.perf_counter() - t0:.1f} s, keys {', '.join(store.keys)}")


@dataclass(frozen=True)
class LeRobotExport:
    """Export a store (any benchmark's) as a LeRobot v3 dataset, written with LeRobot's own library: episodes, task
    texts, actions, other action-like keys as action.* features and other per-step keys as observation.* features,
    cameras as videos, fps.

    Examples:
      bpp lerobot export data/libero/train.zarr --out exports/libero-train --cameras agentview eye_in_hand
      bpp lerobot export data/draw/train.zarr --out exports/draw-train --image-size 96
    """

    store: tyro.conf.Positional[Path]
    out: Path = Path("exports/lerobot")
    """The dataset folder to write."""
    cameras: tuple[str, ...] | None = None
    """Cameras to draw (default: an imported store's own; else every camera of the benchmark's observation presets,
    e.g. image for DrawAnything, agentview and eye_in_hand for LIBERO-Gen; --cameras alone: none)."""
    image_size: int = 0
    """Camera frame size in px (0: the size of the frames the store holds, else 128)."""
    video: bool = True
    """Cameras as videos (LeRobot's default); --no-video stores them as PNG images in the parquet files, lossless."""
    vcodec: str = "libsvtav1"
    """The video codec: libsvtav1 (AV1, LeRobot's default; frames of 32 px or more) or h264."""
    action: str = ""
    """The per-step key exported as action (default: the benchmark's default observation's action key); the other
    action keys become action.* features."""
    state: tuple[str, ...] | None = None
    """Keys concatenated into observation.state (default: those the benchmark's default observation reads; not
    written if the store has a key named state, which becomes observation.state itself)."""
    task_text: Literal["instruction", "id"] = "instruction"
    """What a LeRobot task's text is: the task's instruction (its id if it has none) or its id."""
    fps: int = 0
    """Frames per second (0: the store's, else its simulator's control rate, else 10)."""
    episodes: str = ""
    """Episodes to export: "" (all), "START:STOP" or "0,3,7"."""
    overwrite: bool = False
    """Replace an existing dataset at --out."""

    def __post_init__(self):
        check_fields(
            self,
            ("image_size", self.image_size == 0 or 8 <= self.image_size <= 1024, "0 or in [8, 1024] px"),
            ("vcodec", self.vcodec in VCODECS, f"one of {', '.join(VCODECS)}"),
            ("fps", self.fps >= 0, ">= 0"),
        )


def lerobot_export(args: LeRobotExport) -> None:
    t0 = time.perf_counter()
    store = open_store(args.store)  # any benchmark's, with its derived keys
    out = export_store(
        store,
        args.out,
        cameras=args.cameras,
        image_size=args.image_size,
        video=args.video,
        vcodec=args.vcodec,
        action=args.action,
        state=args.state,
        task_text=args.task_text,
        fps=args.fps,
        episodes=parse_episodes(args.episodes, store.num_episodes),
        overwrite=args.overwrite,
    )
    print(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")


COMMANDS = {
    "import": (LeRobotImport, lerobot_import),
    "export": (LeRobotExport, lerobot_export),
}
"""``bpp lerobot <name>``."""
