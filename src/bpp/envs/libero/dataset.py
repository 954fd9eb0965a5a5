"""Generate LIBERO-Gen demonstrations into the project's episode store.

    python -m bpp.envs.libero.dataset --suite combination --split train --demos 5 --out data/libero/combination.zarr

Each task's problem is written to a private folder and loaded without cameras (physics only, about 10x faster than
rendering). The scripted demonstrator tries seeds until the task has ``--demos`` demonstrations that LIBERO's
predicate accepts, or ``--max-tries`` have been spent. Failures are counted, never stored. Per step the store keeps
the action (7-D OSC_POSE), LIBERO's ``robot0_proprio-state`` and ``object-state`` vectors, and the full simulator
state, so that any camera can be rendered later from the stored state. The store is written atomically (a killed
run leaves no store). Resuming a killed run is not done yet.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.envs.libero.suites import SUITES_BY_NAME, PickPlace

BENCHMARK = "libero_gen"


def _task_job(job) -> tuple[int, list, int]:
    """Worker: demonstrations of one task. Returns (task index, [(seed, Demonstration)], failed tries)."""
    index, task, demos, max_tries, seed = job
    from bpp.envs.libero.bddl import combination_problem
    from bpp.envs.libero.demonstrator import Unsupported, demonstrate
    from bpp.envs.libero.sim import make_env, spatial_problem

    with tempfile.TemporaryDirectory(prefix="libero-task-") as folder:
        problem = Path(folder) / "task.bddl"
        problem.write_text(combination_problem(task, spatial_problem(task.scene.base)))
        env = make_env(problem)
        kept, failed = [], 0
        try:
            for attempt in range(max_tries):
                if len(kept) >= demos:
                    break
                demo_seed = seed * 1_000_003 + index * 1009 + attempt
                try:
                    demo = demonstrate(env, task, demo_seed)
                except Unsupported:
                    return index, [], max_tries
                if demo.success:
                    kept.append((demo_seed, demo))
                else:
                    failed += 1
        finally:
            env.close()
    return index, kept, failed


def generate(
    tasks: list[PickPlace],
    out: Path,
    demos: int = 5,
    max_tries: int = 10,
    seed: int = 0,
    workers: int = 1,
    overwrite: bool = False,
    progress: bool = True,
) -> tuple[EpisodeStore | None, dict]:
    """Demonstrate `tasks` into the store `out`; returns the store (None if no task got a demonstration) and a
    report: tries, successes and failures per place, unsupported tasks, demonstrations per hour."""
    jobs = [(i, t, demos, max_tries, seed) for i, t in enumerate(tasks)]
    t0 = time.perf_counter()
    tries, successes = Counter(), Counter()
    unsupported = []
    config = {"tasks": [t.instruction for t in tasks], "demos": demos, "max_tries": max_tries, "seed": seed}
    writer = EpisodeWriter(out, benchmark=BENCHMARK, config=config, overwrite=overwrite)
    pool = None
    try:
        if workers > 1 and len(jobs) > 1:
            pool = mp.get_context("spawn").Pool(workers)
            results = pool.imap(_task_job, jobs)
        else:
            results = map(_task_job, jobs)
        stored = 0
        for index, kept, failed in tqdm(results, total=len(jobs), desc="demonstrating", disable=not progress):
            task = tasks[index]
            if not kept and failed >= max_tries:
                unsupported.append(task.instruction)
            tries[task.place] += len(kept) + failed
            successes[task.place] += len(kept)
            if not kept:
                continue
            info = {k: v for k, v in task.describe().items() if k != "instruction"}
            task_index = writer.add_task(f"{index:03d}-{task.name}", info, instruction=task.instruction)
            for demo_seed, demo in kept:
                steps = {
                    "action": demo.actions.astype(np.float32),
                    "proprio": demo.observations["robot0_proprio-state"].astype(np.float32),
                    "object_state": demo.observations["object-state"].astype(np.float32),
                    "sim_state": demo.states.astype(np.float64),
                }
                writer.add_episode(steps, task_index, seed=demo_seed)
                stored += 1
    except BaseException:
        writer.abort()
        raise
    finally:
        if pool is not None:
            pool.terminate()
    seconds = time.perf_counter() - t0
    report = {
        "tasks": len(tasks),
        "stored": stored,
        "tries": dict(tries),
        "successes": dict(successes),
        "unsupported": unsupported,
        "seconds": round(seconds, 1),
        "demos_per_hour": round(3600 * stored / max(seconds, 1e-9), 1),
    }
    if stored == 0:
        writer.abort()
        return None, report
    return writer.close(), report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suite", choices=sorted(SUITES_BY_NAME), default="combination")
    parser.add_argument("--split", choices=("train", "test"), default="train")
    parser.add_argument("--tasks", type=int, default=0, help="the first N tasks of the split (0: all)")
    parser.add_argument("--demos", type=int, default=5, help="demonstrations per task")
    parser.add_argument("--max-tries", type=int, default=10, help="seeds tried per task at most")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    for name in ("demos", "max_tries", "workers"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    suite = SUITES_BY_NAME[args.suite]()
    tasks = list(getattr(suite, args.split))[: args.tasks or None]
    try:
        store, report = generate(tasks, args.out, args.demos, args.max_tries, args.seed, args.workers, args.overwrite)
    except (ValueError, RuntimeError, OSError) as err:
        raise SystemExit(f"error: {err}") from None
    for place in sorted(report["tries"]):
        print(f"{place:5s} {report['successes'].get(place, 0)}/{report['tries'][place]} demonstrations succeeded")
    print(
        f"{report['stored']} demonstrations of {report['tasks']} tasks in {report['seconds']} s "
        f"({report['demos_per_hour']} per hour); unsupported: {len(report['unsupported'])}"
    )
    if store is not None:
        print(f"wrote {store}")


if __name__ == "__main__":
    main()
