"""``bpp iphumi process``: a folder of exported recordings -> a store, in parallel over demonstrations, resumable.

Each demonstration is processed on its own (:func:`bpp.benchmarks.iphumi.process.episodes_of`) into a part file
beside the store (``.<store name>.parts/<settings digest>/``), written atomically; a rejected demonstration leaves
its reason there instead. Run the same command again after an interruption and finished demonstrations are not
redone; with new recordings in the folder only they are processed. The store is then written in one go from the
parts (atomically, like every store), with every rejection and its reason in its configuration and on screen.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.iphumi.align import load_mounts
from bpp.benchmarks.iphumi.process import ProcessSettings, episodes_of
from bpp.benchmarks.iphumi.recording import (
    Demonstration,
    RecordingError,
    find_recordings,
    group_demonstrations,
    read_recording,
)
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError
from bpp.recorded.heldout import heldout_path, split_episodes
from bpp.utils import usable_cores, worker_pool, write_json_atomic

BENCHMARK = "iphumi"
"""The benchmark name written into the stores made here (the registry's key)."""

_CALIBRATIONS: dict = {}
"""A worker's gripper calibrations, computed once per calibration recording."""


def parts_folder(out: Path, settings: ProcessSettings) -> Path:
    return out.parent / f".{out.name}.parts" / settings.digest()


def _part_name(group: str) -> str:
    return re.sub(r"[^\w.-]", "_", group)


def _process(group: str, folders: dict[str, str], index: dict[str, str], settings: ProcessSettings, parts: str):
    """Worker: one demonstration -> its part file (or its rejection file). Returns (group, episodes, notes, error)."""
    # OpenCV: the iphumi extra
    import cv2

    cv2.setNumThreads(1)  # one process per core already

    target = Path(parts) / _part_name(group)
    try:
        phones = {side: read_recording(folder) for side, folder in folders.items()}
        episodes, skipped = episodes_of(
            Demonstration(group, phones), {k: Path(v) for k, v in index.items()}, settings, _CALIBRATIONS
        )
    except RecordingError as err:
        target.with_suffix(".json").unlink(missing_ok=True)
        write_json_atomic(target.with_suffix(".rejected.json"), {"group": group, "reason": str(err)})
        return group, 0, [], str(err)
    arrays = {f"{i}/{key}": value for i, episode in enumerate(episodes) for key, value in episode["steps"].items()}
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, target.with_suffix(".npz"))
    meta = {"group": group, "episodes": [{"task": e["task"], "start": e["start"]} for e in episodes], "notes": skipped}
    target.with_suffix(".rejected.json").unlink(missing_ok=True)
    write_json_atomic(target.with_suffix(".json"), meta)  # last: its presence marks the part complete
    return group, len(episodes), skipped, None


def _process_job(job: tuple):
    return _process(*job)


def process_export(
    export: Path,
    out: Path,
    settings: ProcessSettings = ProcessSettings(),
    *,
    workers: int = 0,
    overwrite: bool = False,
    holdout_episodes: int = 0,
    progress: bool = True,
) -> tuple[EpisodeStore, EpisodeStore | None, list[tuple[str, str]]]:
    """Process every demonstration under `export` into the store `out` (and, with `holdout_episodes`, each task's
    last episodes into ``<out>-heldout.zarr``). Returns (store, held-out store or None, [(demonstration, why it was
    left out)])."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    load_mounts(settings.mounts)  # a bad mount file is named before any work
    folders = find_recordings(export)
    if not folders:
        raise UserError(f"{export}: no iPhUMI recordings (folders named <start>_<digits>_<session>_<type>_<side>)")
    rejected: list[tuple[str, str]] = []
    recordings = []
    for folder in folders:
        try:
            recordings.append(read_recording(folder, check_media=False))
        except RecordingError as err:
            rejected.append((folder.name, str(err)))
    demonstrations, invalid = group_demonstrations(recordings)
    rejected += invalid
    if not settings.include_error_correction:
        demonstrations = [d for d in demonstrations if not any(r.is_error_correction for r in d.phones.values())]
    if not demonstrations:
        reasons = "; ".join(f"{g}: {r}" for g, r in rejected[:5])
        raise UserError(f"{export}: no usable demonstration among {len(folders)} recording(s) ({reasons})")
    index = {str(r.name): str(r.folder) for r in recordings}
    parts = parts_folder(out, settings)
    parts.mkdir(parents=True, exist_ok=True)
    todo = [d for d in demonstrations if not _done(parts, d.group)]
    workers = max(1, min(workers or usable_cores(), len(todo) or 1))
    bar = tqdm(
        total=len(demonstrations),
        initial=len(demonstrations) - len(todo),
        desc="process",
        unit="demo",
        disable=not progress,
    )
    jobs = [(d.group, {s: str(r.folder) for s, r in d.phones.items()}, index, settings, str(parts)) for d in todo]
    if workers == 1:
        for job in jobs:
            _process(*job)
            bar.update()
    else:
        # spawned, not forked: a forked child deadlocks on a lock one of OpenCV's or FFmpeg's threads held in the
        # parent; the pool's workers leave Ctrl-C and SIGTERM to this process, which stops them
        with worker_pool(multiprocessing.get_context("spawn"), workers) as pool:
            for _ in pool.imap_unordered(_process_job, jobs):
                bar.update()
    bar.close()
    # the store, from every part (earlier runs' included)
    loaded, notes = [], []
    for demonstration in demonstrations:
        target = parts / _part_name(demonstration.group)
        refusal = target.with_suffix(".rejected.json")
        if refusal.is_file():
            rejected.append((demonstration.group, json.loads(refusal.read_text())["reason"]))
            continue
        meta = json.loads(target.with_suffix(".json").read_text())
        notes += meta["notes"]
        loaded.append((demonstration.group, meta, target.with_suffix(".npz")))
    if not loaded:
        raise UserError(f"{export}: every demonstration was rejected: " + "; ".join(r for _, r in rejected[:5]))
    episodes = [(group, i, e) for group, meta, _ in loaded for i, e in enumerate(meta["episodes"])]
    tasks = sorted({e["task"] for _, _, e in episodes})
    by_task: dict[int, list[int]] = {}
    for number, (_, _, e) in enumerate(episodes):
        by_task.setdefault(tasks.index(e["task"]), []).append(number)
    train, held, _ = split_episodes(by_task, holdout_episodes, 0)
    if holdout_episodes and not held:
        raise UserError(f"nothing is held out: no task has more than {holdout_episodes} episodes")
    config = {
        "source": str(Path(export).resolve()),
        "settings": {**asdict(settings), "mounts": str(settings.mounts) if settings.mounts else None},
        "fps": settings.fps,
        "cameras": [],
        "rejected": [{"demonstration": g, "reason": r} for g, r in rejected],
        "notes": notes,
    }
    files = {group: np.load(path) for group, _, path in loaded}
    first = files[episodes[0][0]]
    config["cameras"] = sorted({k.split("/", 1)[1] for k in first.files if first[k].dtype == np.uint8})
    outputs = [(out, train, "train")] + ([(heldout_path(out), held, "held-out")] if holdout_episodes else [])
    stores = []
    for path, chosen, split in outputs:
        # each episode's demonstration, in store order
        split_config = {**config, "split": split, "demonstrations": [episodes[n][0] for n in chosen]}
        with EpisodeWriter(path, benchmark=BENCHMARK, config=split_config, overwrite=overwrite) as writer:
            task_index: dict[str, int] = {}
            for number in chosen:
                group, i, episode = episodes[number]
                name = episode["task"]
                if name not in task_index:
                    task_index[name] = writer.add_task(_task_id(tasks.index(name), name), instruction=name)
                data = files[group]
                steps = {k.split("/", 1)[1]: data[k] for k in data.files if k.startswith(f"{i}/")}
                writer.add_episode(steps, task_index[name], start_s=episode["start"])
        stores.append(EpisodeStore(path))
    return stores[0], (stores[1] if len(stores) > 1 else None), rejected


def _done(parts: Path, group: str) -> bool:
    """Whether a demonstration's part is complete. A rejected one is tried again: the reason may have gone (a
    calibration recording exported since, a mount file given)."""
    return (parts / _part_name(group)).with_suffix(".json").is_file()


def _task_id(index: int, name: str) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")[:40].rstrip("-")
    return f"{index:03d}-{slug}" if slug else f"{index:03d}"


def process_one(folder: Path, settings: ProcessSettings, export: Path | None = None) -> dict:
    """One demonstration recording (any phone of it) -> one episode of the whole demonstration: {"task", "steps"}.
    Its other phones and its calibration recording are looked up beside it (or under `export`)."""
    recording = read_recording(folder)
    if recording.kind != "demonstration":
        raise RecordingError(f"{folder}: a {recording.kind} recording, not a demonstration")
    root = Path(export) if export is not None else Path(folder).parent
    candidates = find_recordings(root)
    if recording.calibration_name and not any(c.name == recording.calibration_name for c in candidates):
        candidates += find_recordings(root.parent)  # the app's export puts each day in its own folder
    index = {c.name: c for c in candidates}
    phones = {recording.side: recording}
    for side in recording.sides_present:
        name = f"{recording.group}_{side}"
        if side not in phones:
            if name not in index:
                raise RecordingError(f"{folder}: its {side} phone's recording {name} is not beside it")
            phones[side] = read_recording(index[name])
    episodes, _ = episodes_of(Demonstration(recording.group, phones), index, settings, whole=True)
    return episodes[0]


def describe_rejections(rejected: Sequence[tuple[str, str]], limit: int = 20) -> str:
    lines = [f"  {group}: {reason}" for group, reason in rejected[:limit]]
    if len(rejected) > limit:
        lines.append(f"  ... and {len(rejected) - limit} more (the store's config lists them all)")
    return "\n".join(lines)
