"""Write a LIBERO-Gen suite's tasks: one BDDL problem per task and a ``tasks.json`` index with the split.

    bpp libero tasks --suite combination --out data/libero/combination
    bpp libero tasks --suite combination --out data/libero/combination --init-states 50   # + LIBERO init files

It prints each held-out task with the counts the paper's appendix lists: for Combination, the training tasks that
share its pick and its place; for Chain, the training chains that share its first step and second-step object.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.libero.dataset import problem_text, task_id
from bpp.benchmarks.libero.sim import make_env, reset_env
from bpp.benchmarks.libero.suites import Suite
from bpp.errors import UserError


def sample_initial_states(problem: Path, count: int) -> np.ndarray:
    """(count, S) flattened simulator states of LIBERO's placement sampler for seeds 0 .. count-1 of the BDDL problem
    file `problem`: the states LIBERO's own evaluation loads with ``env.set_init_state`` (its ``.pruned_init``
    files hold the same kind of array). Takes an env creation (seconds) plus about 0.3 s per state."""
    env = make_env(problem)
    try:
        states = []
        for seed in range(count):
            reset_env(env, seed)
            states.append(env.env.sim.get_state().flatten())
    finally:
        env.close()
    return np.stack(states)


def write_suite(suite: Suite, out: Path, overwrite: bool = False, init_states: int = 0) -> Path:
    """Write `suite` into the folder `out`: ``problems/<id>.bddl`` and ``tasks.json``, and with `init_states` > 0
    ``problems/<id>.init.npz`` (``states``: that many initial states per task; not for LIBERO's own suites, whose
    initial states LIBERO ships). Returns the index path. The folder is built beside `out` and renamed into place,
    so an interrupted run leaves nothing half-written."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if out.exists() and not (out / "tasks.json").is_file():
        raise UserError(f"{out} exists and is not a written suite (no tasks.json); only a suite is ever replaced")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "problems").mkdir(parents=True)
    index = {"suite": suite.name, "train": [], "test": []}
    states = init_states if not suite.original else 0
    bar = tqdm(total=len(suite.train) + len(suite.test), desc="initial states", unit="task", disable=not states)
    for split, tasks in (("train", suite.train), ("test", suite.test)):
        for i, task in enumerate(tasks):
            name = task_id(split, i, task)
            (tmp / "problems" / f"{name}.bddl").write_text(problem_text(task, suite.original))
            entry = {"id": name, **task.describe(), "problem": f"problems/{name}.bddl"}
            if states:
                np.savez(
                    tmp / "problems" / f"{name}.init.npz",
                    states=sample_initial_states(tmp / "problems" / f"{name}.bddl", states),
                )
                entry["init_states"] = f"problems/{name}.init.npz"
                bar.update()
            if split == "test":
                entry["similar"] = suite.similar_counts(task)
            index[split].append(entry)
    bar.close()
    (tmp / "tasks.json").write_text(json.dumps(index, indent=1))
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return out / "tasks.json"
