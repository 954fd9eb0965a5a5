"""Held-out episodes of recorded demonstrations: which episodes of each task a store of recordings keeps back for
open-loop evaluation (:mod:`bpp.recorded.replay`), and where that second store goes."""

from __future__ import annotations

from pathlib import Path

from bpp.errors import UserError


def split_episodes(by_task: dict[int, list[int]], holdout_episodes: int, holdout_tasks: int):
    """(training episodes, held-out episodes, tasks too small to hold episodes out of) for episodes grouped by task."""
    tasks = sorted(by_task)
    if holdout_tasks >= len(tasks) and holdout_tasks:
        raise UserError(f"--holdout-tasks {holdout_tasks} leaves no task to train on (the selection has {len(tasks)})")
    held_tasks = set(tasks[len(tasks) - holdout_tasks :]) if holdout_tasks else set()
    train, held, whole = [], [], []
    for task in tasks:
        episodes = sorted(by_task[task])
        if task in held_tasks:
            held += episodes
        elif holdout_episodes and len(episodes) > holdout_episodes:
            train += episodes[:-holdout_episodes]
            held += episodes[-holdout_episodes:]
        else:
            train += episodes
            whole += [task] if holdout_episodes else []
    return sorted(train), sorted(held), whole


def heldout_path(out: Path) -> Path:
    """``data/x.zarr`` -> ``data/x-heldout.zarr``."""
    return out.with_name(f"{out.stem}-heldout{out.suffix}")
