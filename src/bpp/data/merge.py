"""Merging episode stores into one: pieces generated on several machines, or demonstrations of a few tasks added
later.

Stores merge when they hold data of one kind: one benchmark; the same per-step keys, episode columns and per-task
arrays, each of the same shape (past the first axis) and dtype; and the same :data:`READ_CONFIG` entries, which readers
take from a store's config. Anything else in their configs may differ, as pieces of one dataset do (the seed, the
number of tasks): the merged header keeps the first store's config and lists every source's under ``merged_from``. A
task in several stores (the same id) must be the same task in each: instruction, info and per-task arrays. A refusal
names the stores and the field they differ in.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from bpp.data.integrity import StoreError
from bpp.data.store import EpisodeStore, EpisodeWriter

READ_CONFIG = ("cameras", "features", "fps", "robot_type")
"""Config entries that readers take from a store's header (its cameras, a LeRobot dataset's feature names and robot,
the control rate): stores that differ in one hold data that cannot be read as one store."""

_MISSING = object()


def _shown(value) -> str:
    """A value as a refusal shows it: its repr, cut at 80 characters."""
    text = "nothing" if value is _MISSING else repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def _refuse_overlaps(stores: list[EpisodeStore], out: Path) -> None:
    """Refuse a merge whose inputs include one store twice (by any path to it), or whose output is an input, lies
    inside one or holds one: the first would double every demonstration, the others change an input."""
    for i, store in enumerate(stores):
        for other in stores[:i]:
            if os.path.samefile(store.path, other.path):
                raise StoreError(
                    f"{store.path} is {other.path} given again: a store merged with itself holds each of its "
                    "demonstrations twice"
                )
    target = out.resolve()
    for store in stores:
        source = store.path.resolve()
        if target == source:
            raise StoreError(f"{out}: the merge would be written over its input {store.path}; choose a new path")
        if source in target.parents:
            raise StoreError(f"{out}: the merge would be written inside its input {store.path}; choose a path outside")
        if target in source.parents:
            raise StoreError(f"{out}: the merge would replace a folder holding its input {store.path}")


def _layout(store: EpisodeStore) -> dict[str, dict[str, tuple[tuple[int, ...], str]]]:
    """What the store's arrays hold, by kind and name: (shape past the first axis, dtype), from metadata alone."""
    kinds = {
        "per-step keys": {k: store.spec(f"data/{k}") for k in store.stored_keys},
        "episode columns": {k: store.spec(f"meta/{k}") for k in store.columns},
        "per-task arrays": {k: store.spec(f"tasks/{k}") for k in store.task_keys},
    }
    return {kind: {k: (shape, str(dtype)) for k, (shape, dtype) in specs.items()} for kind, specs in kinds.items()}


def _refuse_incompatible(first: EpisodeStore, store: EpisodeStore) -> None:
    """Refuse `store` beside `first` if their data are not of one kind (see the module's description), naming the
    field they differ in."""
    if store.benchmark != first.benchmark:
        raise StoreError(
            f"{store.path} holds {store.benchmark} data and {first.path} {first.benchmark} data; merge stores of one "
            "benchmark"
        )
    ours, theirs = _layout(first), _layout(store)
    for kind, specs in theirs.items():
        if sorted(specs) != sorted(ours[kind]):
            raise StoreError(f"{store.path} has {kind} {sorted(specs)}, {first.path} {sorted(ours[kind])}")
        for name, (shape, dtype) in specs.items():
            if (shape, dtype) != ours[kind][name]:
                known_shape, known_dtype = ours[kind][name]
                raise StoreError(
                    f"{kind[:-1]} {name!r} differs: rows of shape {shape} and dtype {dtype} in {store.path}, of "
                    f"shape {known_shape} and dtype {known_dtype} in {first.path}"
                )
    for key in READ_CONFIG:
        value, known = store.config.get(key, _MISSING), first.config.get(key, _MISSING)
        if value != known:
            raise StoreError(
                f"config entry {key!r} differs: {_shown(value)} in {store.path}, {_shown(known)} in {first.path} "
                "(readers take it from the store)"
            )


def _task_difference(known: dict, task: dict, known_arrays: dict, arrays: dict) -> str | None:
    """The first field in which two entries of one task id differ (instruction, an info entry, a per-task array), or
    None if they agree."""
    if known["instruction"] != task["instruction"]:
        return f"its instruction ({_shown(known['instruction'])}, {_shown(task['instruction'])})"
    for name in sorted(set(known["info"]) | set(task["info"])):
        before, after = known["info"].get(name, _MISSING), task["info"].get(name, _MISSING)
        if before != after:
            return f"its info entry {name!r} ({_shown(before)}, {_shown(after)})"
    for name, value in arrays.items():
        if not np.array_equal(known_arrays[name], value):
            return f"its per-task array {name!r}"
    return None


def _episode_digest(steps: dict[str, np.ndarray]) -> bytes:
    """SHA-256 of an episode's per-step arrays (keys, dtypes, shapes and bytes)."""
    digest = hashlib.sha256()
    for key in sorted(steps):
        value = np.ascontiguousarray(steps[key])
        digest.update(f"{key}\0{value.dtype.str}\0{value.shape}\0".encode())
        digest.update(value.tobytes())
    return digest.digest()


def merge_stores(paths: Iterable[str | Path], out: str | Path, overwrite: bool = False) -> EpisodeStore:
    """One store of every episode of the stores at `paths` (data of one kind: see the module's description), written
    atomically to `out`: e.g. pieces generated on several machines, or demonstrations of a few tasks added later.
    A task in several stores (the same id) becomes one task with all their episodes; its instruction, info and
    per-task arrays must agree. The merged header keeps the first store's generation config and lists every
    source (path, fingerprint, config) under ``merged_from``; the statistics are those of the merged episodes.

    Refused, naming the stores and the field: stores whose data are not of one kind, and a task id that names
    different tasks. Refused too: a store given twice, an episode that two of the stores hold (a store merged with a
    copy of itself, or with a merge that includes it: its demonstrations would count twice), and an output that is an
    input, lies inside one or holds one."""
    stores = [EpisodeStore(p) for p in paths]
    if len(stores) < 2:
        raise StoreError("merging needs at least two stores")
    _refuse_overlaps(stores, Path(out))
    first = stores[0]
    for s in stores[1:]:
        _refuse_incompatible(first, s)
    with EpisodeWriter(out, benchmark=first.benchmark, config=first.config, overwrite=overwrite) as writer:
        merged: dict[str, tuple[int, dict, dict, Path]] = {}  # task id -> (index, entry, arrays, the store's path)
        seen: dict[bytes, tuple[int, int]] = {}  # episode digest -> (store, episode) that first held it
        for n, s in enumerate(stores):
            columns = [k for k in s.columns if k != "task_index"]
            remap = []
            for t, task in enumerate(s.tasks):
                arrays = {k: s.task_array(k, t) for k in s.task_keys}  # the same keys in every store (checked above)
                if task["id"] not in merged:
                    index = writer.add_task(task["id"], task["info"], instruction=task["instruction"], **arrays)
                    merged[task["id"]] = (index, task, arrays, s.path)
                index, known, known_arrays, holder = merged[task["id"]]
                difference = _task_difference(known, task, known_arrays, arrays)
                if difference is not None:
                    raise StoreError(
                        f"task {task['id']!r} of {s.path} is another task than {task['id']!r} of {holder}: "
                        f"{difference} differs; a task id must name one task in every store merged"
                    )
                remap.append(index)
            task_index = s.column("task_index")
            for e in range(s.num_episodes):
                steps = s.episode(e, s.stored_keys)
                m, f = seen.setdefault(_episode_digest(steps), (n, e))
                if m != n:
                    raise StoreError(
                        f"episode {e} of {s.path} is episode {f} of {stores[m].path} again: merged, it would count "
                        "twice (is one store a copy of the other, or a merge that includes it?)"
                    )
                extra = {k: s.column(k)[e] for k in columns}  # a scalar, or an array (a goal image)
                writer.add_episode(steps, remap[int(task_index[e])], **extra)
        writer.root.attrs["merged_from"] = [
            {"path": str(s.path), "fingerprint": s.fingerprint(), "config": s.config} for s in stores
        ]
    return EpisodeStore(out)
