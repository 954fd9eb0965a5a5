"""Do stored LIBERO-Gen demonstrations replay? Each one's actions executed open-loop in a new env from its stored
first state (with its fixtures) must pass through its stored states and reach its goal.

    python bench/libero_demo_replay.py STORE [STORE ...]
    python bench/libero_demo_replay.py --generate data/replay.zarr --num-tasks 50 --demos-per-task 2 --workers 1

For every demonstration: whether the replay reached LIBERO's goal, whether its states equal the stored ones bit for
bit, and how far its final state ends from the stored one. For contrast, the same replay with the actions rounded to
float32 (how they were stored before): the physics is chaotic, so the rounding alone changes outcomes. Physics only:
about 5 s per demonstration and variant on one core. Needs the `libero` extra.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.dataset import episode_fixtures
from bpp.benchmarks.libero.rollouts import task_problem
from bpp.benchmarks.libero.sim import make_env, replay
from bpp.cli import main as bpp
from bpp.data.store import EpisodeStore


def replay_store(store: EpisodeStore, rounded: bool) -> list[dict]:
    rows = []
    actions_key = "executed_action" if "executed_action" in store.keys else "action"
    with tempfile.TemporaryDirectory(prefix="libero-replay-") as folder:
        envs: dict[int, object] = {}  # the current task's env only: one holds a few hundred MB
        try:
            for episode in range(store.num_episodes):
                task = int(store.column("task_index")[episode])
                if task not in envs:
                    for env in envs.values():
                        env.close()
                    envs.clear()
                    path = Path(folder) / f"task-{task}.bddl"
                    path.write_text(task_problem(store, episode))
                    envs[task] = make_env(path)
                steps = store.episode(episode, ["sim_state", actions_key])
                actions = steps[actions_key]
                if rounded:
                    actions = actions.astype(np.float32).astype(np.float64)
                seed, fixtures = int(store.column("seed")[episode]), episode_fixtures(store, episode)
                states, success = replay(envs[task], seed, steps["sim_state"], actions, fixtures)
                gap = np.abs(states[:-1] - steps["sim_state"]).max(axis=1)
                rows.append({"success": success, "exact": not gap.any(), "final_gap": float(gap[-1])})
        finally:
            for env in envs.values():
                env.close()
    return rows


def summary(label: str, rows: list[dict]) -> str:
    n = len(rows)
    success = sum(r["success"] for r in rows)
    exact = sum(r["exact"] for r in rows)
    gaps = np.array([r["final_gap"] for r in rows])
    return (
        f"| {label} | {n} | {success} ({100 * success / n:.1f}%) | {exact} ({100 * exact / n:.1f}%) | "
        f"{np.median(gaps):.3g} | {gaps.max():.3g} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stores", type=Path, nargs="*")
    parser.add_argument("--generate", type=Path, help="first generate this store (flags below)")
    parser.add_argument("--suite", default="combination")
    parser.add_argument("--num-tasks", type=int, default=50)
    parser.add_argument("--demos-per-task", type=int, default=2)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--variants", nargs="+", default=["stored", "float32"], choices=["stored", "float32"])
    args = parser.parse_args()
    stores = list(args.stores)
    if args.generate:
        if not args.generate.exists():
            bpp(["libero", "generate", "--out", str(args.generate), "--suite", args.suite, "--num-tasks",
                 str(args.num_tasks), "--demos-per-task", str(args.demos_per_task), "--goal-size", "0",
                 "--workers", str(args.workers)])  # fmt: skip
        stores.append(args.generate)
    print("| actions replayed | demonstrations | reached the goal | states bit for bit | final gap: median | max |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for path in stores:
        store = EpisodeStore(path)
        for rounded in [variant == "float32" for variant in args.variants]:
            t0 = time.perf_counter()
            rows = replay_store(store, rounded)
            label = f"{path.name}: {'rounded to float32' if rounded else 'as stored'}"
            print(summary(label, rows), f"<!-- {time.perf_counter() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
