"""Write a LIBERO-Gen suite's tasks: one BDDL problem per task and a ``tasks.json`` index with the split.

    bpp libero tasks --suite combination --out data/libero/combination

It prints each held-out task with the counts the paper's appendix lists: for Combination, the training tasks that
share its pick and its place; for Chain, the training chains that share its first step and second-step object.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from bpp.envs.libero.suites import Suite


def write_suite(suite: Suite, out: Path, overwrite: bool = False) -> Path:
    """Write `suite` into the folder `out`: ``problems/<id>.bddl`` and ``tasks.json``. Returns the index path.
    The folder is built beside `out` and renamed into place, so an interrupted run leaves nothing half-written."""
    from bpp.envs.libero.dataset import problem_text, task_id

    out = Path(out)
    if out.exists() and not overwrite:
        raise ValueError(f"{out} exists; pass --overwrite to replace it")
    if out.exists() and not (out / "tasks.json").is_file():
        raise ValueError(f"{out} exists and is not a written suite (no tasks.json); only a suite is ever replaced")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "problems").mkdir(parents=True)
    index = {"suite": suite.name, "train": [], "test": []}
    for split, tasks in (("train", suite.train), ("test", suite.test)):
        for i, task in enumerate(tasks):
            name = task_id(split, i, task)
            (tmp / "problems" / f"{name}.bddl").write_text(problem_text(task, suite.original))
            entry = {"id": name, **task.describe(), "problem": f"problems/{name}.bddl"}
            if split == "test":
                entry["similar"] = suite.similar_counts(task)
            index[split].append(entry)
    (tmp / "tasks.json").write_text(json.dumps(index, indent=1))
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return out / "tasks.json"
