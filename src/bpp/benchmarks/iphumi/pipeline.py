"""``bpp iphumi process``: a folder of exported recordings -> a store, in parallel over demonstrations, resumable.

Each demonstration is processed on its own (:func:`bpp.benchmarks.iphumi.process.episodes_of`) into a part file
beside the store (``.<store name>.parts/<settings digest>/``), written atomically; a rejected demonstration leaves
its reason there instead. A part is named by its demonstration and a hash of the content of every file it is made
from (:func:`part_key`), so run the same command again after an interruption and finished demonstrations are not
redone, with new recordings in the folder only they are processed, and a recording changed since (a corrected label,
new poses, a new calibration recording) is processed again. The store is then written in one go from the parts
(atomically, like every store), with every rejection and its reason in its configuration and on screen.

What is known to make the command fail is refused before any work: an existing store without ``--overwrite``, two
recordings of one name, demonstrations whose episodes could not share a store (single-arm and bimanual). Every
folder that looks like a recording but is left out is named with its reason before any work too.
"""

from __future__ import annotations

import functools
import json
import multiprocessing
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.iphumi.align import load_mounts
from bpp.benchmarks.iphumi.process import ProcessSettings, calibration_files, episodes_of, hash_files, layout
from bpp.benchmarks.iphumi.recording import (
    Demonstration,
    RecordingError,
    group_demonstrations,
    index_recordings,
    read_recording,
    scan_export,
)
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError
from bpp.recorded.heldout import heldout_path, split_episodes
from bpp.utils import atomic_path, usable_cores, worker_pool, write_json_atomic

BENCHMARK = "iphumi"
"""The benchmark name written into the stores made here (the registry's key)."""

_CALIBRATIONS: dict = {}
"""A worker's gripper calibrations, computed once per calibration recording."""


def parts_folder(out: Path, settings: ProcessSettings) -> Path:
    return out.parent / f".{out.name}.parts" / settings.digest()


def part_key(demonstration: Demonstration, index: Mapping[str, Path], settings: ProcessSettings) -> str:
    """What a demonstration's part is kept by: a hash of its name and of every file its episodes are made from with
    `settings` (each phone's JSON: times, poses, labels; the videos read; each gripper's calibration recording)."""
    paths = []
    for side, recording in sorted(demonstration.phones.items()):
        paths.append(recording.json_path)
        if "rgb" in settings.cameras:
            paths.append(recording.rgb_path)
        if side == "head":
            continue
        paths.append(recording.ultrawide_path)
        if "depth" in settings.cameras:
            paths.append(recording.depth_path)
        if recording.calibration_name in index:
            paths += calibration_files(Path(index[recording.calibration_name]))
    return hash_files(paths, demonstration.group)[:16]


def part_path(parts: Path, group: str, key: str, suffix: str) -> Path:
    """A part's file: the demonstration's name made safe for a file name, its :func:`part_key`, then `suffix`
    (appended: a name holds dots, so Path.with_suffix would cut it at the start time's milliseconds)."""
    return parts / f"{_part_name(group)}-{key}{suffix}"


def _part_name(group: str) -> str:
    return re.sub(r"[^\w.-]", "_", group)


def _process(group: str, folders: dict[str, str], index: dict[str, str], settings: ProcessSettings, parts: str, key):
    """Worker: one demonstration -> its part file (or its rejection file). Returns (group, episodes, notes, error)."""
    # OpenCV: the iphumi extra
    import cv2

    cv2.setNumThreads(1)  # one process per core already

    part = functools.partial(part_path, Path(parts), group, key)
    try:
        phones = {side: read_recording(folder) for side, folder in folders.items()}
        episodes, skipped = episodes_of(
            Demonstration(group, phones), {k: Path(v) for k, v in index.items()}, settings, _CALIBRATIONS
        )
    except RecordingError as err:
        part(".json").unlink(missing_ok=True)
        write_json_atomic(part(".rejected.json"), {"group": group, "reason": str(err)})
        return group, 0, [], str(err)
    arrays = {f"{i}/{name}": value for i, episode in enumerate(episodes) for name, value in episode["steps"].items()}
    with atomic_path(part(".npz")) as tmp:  # complete or absent, a full disk named
        np.savez(tmp, **arrays)
    meta = {"group": group, "episodes": [{"task": e["task"], "start": e["start"]} for e in episodes], "notes": skipped}
    part(".rejected.json").unlink(missing_ok=True)
    write_json_atomic(part(".json"), meta)  # last: its presence marks the part complete
    return group, len(episodes), skipped, None


def _process_job(job: tuple):
    return _process(*job)


def gather(export: Path, settings: ProcessSettings) -> tuple[list[Demonstration], dict[str, Path], list]:
    """The demonstrations under `export` to process, every recording's folder by name, and [(recording or
    demonstration, why it is left out)], each also printed as a warning before any work. Two recordings of one name
    are refused: which one a demonstration is made of would be a guess."""
    folders, left_out = scan_export(export)
    index = index_recordings(folders)
    rejected = [(folder.relative_to(export).as_posix(), reason) for folder, reason in left_out]
    if not folders:
        raise UserError(
            f"{export}: no iPhUMI recordings (folders named <start>_<digits>_<session>_<type>_<side>)"
            + "".join(f"; {name}: {reason}" for name, reason in rejected[:5])
        )
    recordings = []
    for folder in folders:
        try:
            recordings.append(read_recording(folder, check_media=False))
        except RecordingError as err:
            rejected.append((folder.name, str(err)))
    demonstrations, invalid = group_demonstrations(recordings)
    rejected += invalid
    unwanted = {d.group: why for d in demonstrations if (why := _unwanted(d, settings))}
    rejected += sorted(unwanted.items())
    demonstrations = [d for d in demonstrations if d.group not in unwanted]
    for name, reason in rejected:
        print(f"[iphumi process] warning: leaving out {name}: {reason}", file=sys.stderr)
    if not demonstrations:
        reasons = "; ".join(f"{g}: {r}" for g, r in rejected[:5])
        raise UserError(f"{export}: no usable demonstration among {len(folders)} recording(s) ({reasons})")
    return demonstrations, index, rejected


def _unwanted(demonstration: Demonstration, settings: ProcessSettings) -> str | None:
    """Why the settings leave a complete demonstration out before any work (None if they do not)."""
    phones = demonstration.phones
    if not settings.include_error_correction and any(r.is_error_correction for r in phones.values()):
        return "marked as an error correction (left out by --no-include-error-correction)"
    lacking = [side for side in demonstration.grippers if not phones[side].has_depth]
    if "depth" in settings.cameras and lacking:
        return f"--cameras asks for depth, which its {' and '.join(lacking)} phone did not record"
    return None


def check_layouts(demonstrations: Sequence[Demonstration], settings: ProcessSettings) -> None:
    """Refuse, before any work, demonstrations whose episodes cannot share a store (single-arm and bimanual, with and
    without a head camera), naming which are which."""
    layouts: dict[str, list[str]] = {}
    for demonstration in demonstrations:
        layouts.setdefault(layout(demonstration, settings), []).append(demonstration.group)
    if len(layouts) > 1:
        kinds = "; ".join(
            f"{kind} ({len(groups)}): {', '.join(groups[:10])}{', ...' if len(groups) > 10 else ''}"
            for kind, groups in sorted(layouts.items(), key=lambda item: len(item[1]))
        )
        raise UserError(
            f"the recordings mix {' and '.join(sorted(layouts))} demonstrations, whose episodes have different keys "
            f"and cannot share a store; process each kind from its own folder: {kinds}"
        )


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
    last episodes into ``<out>-heldout.zarr``). Returns (store, held-out store or None, [(recording or demonstration,
    why it was left out)]); what is left out before processing is also printed as a warning (:func:`gather`)."""
    out = Path(out)
    for path in [out] + ([heldout_path(out)] if holdout_episodes else []):
        if path.exists() and not overwrite:
            raise UserError(f"{path} exists; pass --overwrite to replace it")
    load_mounts(settings.mounts)  # a bad mount file is named before any work
    demonstrations, index, rejected = gather(export, settings)
    check_layouts(demonstrations, settings)
    parts = parts_folder(out, settings)
    parts.mkdir(parents=True, exist_ok=True)
    keys = {d.group: part_key(d, index, settings) for d in demonstrations}
    todo = [d for d in demonstrations if not part_path(parts, d.group, keys[d.group], ".json").is_file()]
    workers = max(1, min(workers or usable_cores(), len(todo) or 1))
    bar = tqdm(
        total=len(demonstrations),
        initial=len(demonstrations) - len(todo),
        desc="process",
        unit="demo",
        disable=not progress,
    )
    folders = {name: str(folder) for name, folder in index.items()}
    jobs = [
        (d.group, {s: str(r.folder) for s, r in d.phones.items()}, folders, settings, str(parts), keys[d.group])
        for d in todo
    ]
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
    # the store, from every part (earlier runs' included); a rejected demonstration is tried again in the next run
    # (its reason may have gone: a calibration recording exported since, a mount file given)
    loaded, notes = [], []
    for demonstration in demonstrations:
        part = functools.partial(part_path, parts, demonstration.group, keys[demonstration.group])
        if part(".rejected.json").is_file():
            rejected.append((demonstration.group, json.loads(part(".rejected.json").read_text())["reason"]))
            continue
        meta = json.loads(part(".json").read_text())
        notes += meta["notes"]
        loaded.append((demonstration.group, meta, part(".npz")))
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
    found, left_out = scan_export(root)
    if recording.calibration_name and not any(f.name == recording.calibration_name for f in found):
        more, more_left_out = scan_export(root.parent)  # the app's export puts each day in its own folder
        found, left_out = found + more, left_out + more_left_out
    index = index_recordings(found)
    why = {f.name: f" ({reason})" for f, reason in left_out}
    phones = {recording.side: recording}
    for side in recording.sides_present:
        name = f"{recording.group}_{side}"
        if side not in phones:
            if name not in index:
                raise RecordingError(
                    f"{folder}: its {side} phone's recording {name} is not beside it{why.get(name, '')}"
                )
            phones[side] = read_recording(index[name])
    episodes, _ = episodes_of(Demonstration(recording.group, phones), index, settings, whole=True)
    return episodes[0]


def describe_rejections(rejected: Sequence[tuple[str, str] | str], limit: int = 20) -> str:
    """Indented lines of what was left out ((name, reason) or a line each), the first `limit` of them."""
    lines = [f"  {item if isinstance(item, str) else ': '.join(item)}" for item in rejected[:limit]]
    if len(rejected) > limit:
        lines.append(f"  ... and {len(rejected) - limit} more (the store's config lists them all)")
    return "\n".join(lines)
