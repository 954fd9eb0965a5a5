"""``bpp iphumi process|prompt|synth|plot``."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated

import tyro

from bpp.benchmarks.iphumi.pipeline import describe_rejections, process_export
from bpp.benchmarks.iphumi.process import ProcessSettings
from bpp.benchmarks.iphumi.prompt import hand_off
from bpp.benchmarks.iphumi.synthetic import SyntheticSettings, write_export
from bpp.benchmarks.iphumi.viz import plot_episodes
from bpp.data.store import EpisodeStore
from bpp.errors import require_extra
from bpp.utils import check_fields


@dataclass(frozen=True)
class IphumiProcess(ProcessSettings):
    """Process a folder of iPhUMI recordings (the app's export: demonstrations and their gripper calibration runs)
    into a store that bpp train and bpp serve use like any other: one task per task label, one episode per labelled
    segment, poses relative to the episode's start, gripper width from the finger tags, images letterboxed.

    Demonstrations are processed in parallel and kept beside the store by the content of their recordings, so the
    same command resumes after an interruption and processes only new or changed recordings when more are exported.
    Every recording or demonstration left out is listed with its reason; an export mixing single-arm and bimanual
    demonstrations is refused before any work.

    Examples:
      bpp iphumi process /media/sd/iphumi_export --out data/iphumi/cups.zarr --holdout-episodes 1
      bpp iphumi process exports/ --out data/iphumi/fold.zarr --cameras rgb ultrawide --image-size 128
    """

    export: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="EXPORT_DIR")] = Path()
    out: Path = Path("data/iphumi/recordings.zarr")
    """Store to write (a .zarr folder)."""
    holdout_episodes: int = 0
    """Per task, its last N episodes go to a second store, STORE-heldout.zarr, for open-loop evaluation."""
    workers: int = 0
    """Processes (0: one per core)."""
    overwrite: bool = False
    """Replace existing stores."""

    def __post_init__(self):
        super().__post_init__()
        check_fields(
            self,
            ("export", str(self.export) not in ("", "."), "the folder of exported recordings"),
            ("holdout_episodes", self.holdout_episodes >= 0, ">= 0"),
            ("workers", self.workers >= 0, ">= 0"),
        )


def iphumi_process(args: IphumiProcess) -> None:
    require_extra("cv2", "iphumi")
    t0 = time.perf_counter()
    settings = ProcessSettings(**{f.name: getattr(args, f.name) for f in fields(ProcessSettings)})
    store, held, rejected = process_export(
        args.export,
        args.out,
        settings,
        workers=args.workers,
        overwrite=args.overwrite,
        holdout_episodes=args.holdout_episodes,
    )
    print(f"wrote {store}")
    if held is not None:
        print(f"wrote {held} (held out: evaluate with --tasks {held.path})")
    seconds = store.num_steps / settings.fps
    print(
        f"  {time.perf_counter() - t0:.1f} s; {store.num_episodes} episodes ({seconds:.0f} s at {settings.fps:g} Hz) "
        f"of {len(store.tasks)} tasks; keys {', '.join(store.keys)}"
    )
    if rejected:
        print(f"left out {len(rejected)} recording(s) or demonstration(s):\n{describe_rejections(rejected)}")
    notes = store.config.get("notes") or []
    if notes:
        print(f"left out {len(notes)} task segment(s):\n{describe_rejections(notes)}")


@dataclass(frozen=True)
class IphumiPrompt:
    """Send one iPhUMI demonstration to a running policy server (bpp serve) as its behavior prompt: the recording is
    processed for the served model (its cameras, image size and control rate) and uploaded over the server's
    authenticated API. A robot client prompted with the printed handle, or with upload:latest (the newest upload),
    runs it: a person demonstrates with the phone, and the robot does it.

    Examples:
      bpp iphumi prompt exports/2026-01-15/2026-01-15T09-00-25.000Z_67325_lab_demonstration_right
      BPP_SERVE_TOKEN=secret bpp iphumi prompt REC --server ws://robot-pc:8000
    """

    recording: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RECORDING")]
    server: str = "ws://127.0.0.1:8000"
    """The policy server's address."""
    token: str = ""
    """The server's token (default: $BPP_SERVE_TOKEN)."""
    export: Path | None = None
    """Where the recording's other phones and gripper calibration are (default: beside it, and the folder above)."""
    mounts: Path | None = None
    """Phone mount calibrations for phones other than the built-in ones (see bpp iphumi process --help)."""
    check: bool = True
    """Start one episode with the new prompt and time its first action (the robot's episodes are not touched)."""


def iphumi_prompt(args: IphumiPrompt) -> None:
    require_extra("cv2", "iphumi")
    require_extra("websockets", "serve")
    token = args.token or os.environ.get("BPP_SERVE_TOKEN") or None
    result = hand_off(args.recording, args.server, token, ProcessSettings(mounts=args.mounts), args.export, args.check)
    print(f"prompt {result.handle}: {result.task!r}, {result.steps} steps, {result.upload_bytes / 1024:.0f} KiB")
    timing = f"  processed in {result.process_s:.2f} s, uploaded in {result.upload_s * 1e3:.0f} ms"
    if result.first_action_s is not None:
        timing += f", first action {result.first_action_s * 1e3:.0f} ms after the upload"
    print(timing)
    print(f"  robots prompted with {result.handle} or upload:latest run it")


@dataclass(frozen=True)
class IphumiSynth(SyntheticSettings):
    """Write synthetic iPhUMI recordings, exactly as the phone app exports them, with known ground truth: each task a
    procedural drawing traced by the gripper on a table, finger tags drawn at the true gripper width. For trying the
    workflow without a phone, and for tests.

    Examples:
      bpp iphumi synth data/iphumi/synthetic --demonstrations 12 --tasks 4
      bpp iphumi synth data/iphumi/bimanual --bimanual --head --depth
    """

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")] = Path("data/iphumi/synthetic")


def iphumi_synth(args: IphumiSynth) -> None:
    require_extra("cv2", "iphumi")
    t0 = time.perf_counter()
    settings = SyntheticSettings(**{f.name: getattr(args, f.name) for f in fields(SyntheticSettings)})
    truths = write_export(args.out, settings)
    seconds = sum(t.times[-1] - t.times[0] for t in truths.values())
    print(
        f"wrote {len(truths)} demonstration recording(s) ({seconds:.0f} s) and their gripper calibration to "
        f"{args.out} ({time.perf_counter() - t0:.1f} s)"
    )


@dataclass(frozen=True)
class IphumiPlot:
    """A picture of processed demonstrations: the gripper's path in 3-D (coloured by time, where the gripper is
    closed drawn thicker), its width over time, and main-camera frames along the way.

    Example:
      bpp iphumi plot data/iphumi/recordings.zarr --episodes 0 1 --out docs/img/iphumi_episode.png
    """

    store: Annotated[Path, tyro.conf.Positional]
    episodes: tuple[int, ...] = (0,)
    out: Path = Path("iphumi_episodes.png")


def iphumi_plot(args: IphumiPlot) -> None:
    store = EpisodeStore(args.store)
    plot_episodes(store, list(args.episodes), args.out)
    print(f"wrote {args.out}")


COMMANDS = {
    "process": (IphumiProcess, iphumi_process),
    "prompt": (IphumiPrompt, iphumi_prompt),
    "synth": (IphumiSynth, iphumi_synth),
    "plot": (IphumiPlot, iphumi_plot),
}
"""``bpp iphumi <name>``."""
