"""Do stored LIBERO-Gen demonstrations replay? Each one's actions executed open-loop in a new env from its stored
first state (with its fixtures) must pass through its stored states and reach its goal.

    python bench/libero_demo_replay.py STORE [STORE ...]
    python bench/libero_demo_replay.py --generate data/replay.zarr --num-tasks 50 --demos-per-task 2 --workers 1
    python bench/libero_demo_replay.py --generate data/drawer.zarr --task-indices 30 31 32 33 34 35 --variants file

For every demonstration: whether the replay reached LIBERO's goal, whether its states equal the stored ones bit for
bit, and how far its final state ends from the stored one. Variants: `stored` (the actions as stored, in the scene
rebuilt from the seed and fixtures), `float32` (the actions rounded to float32: the physics is chaotic, so the
rounding alone changes outcomes) and `file` (the actions as stored, in the scene its exported ``model_file``
compiles, as LIBERO's own replay loads it). Physics only: about 5 s per demonstration and variant on one core.
Needs the `libero` extra.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.dataset import episode_fixtures
from bpp.benchmarks.libero.export import scene_xml
from bpp.benchmarks.libero.rollouts import task_problem
from bpp.benchmarks.libero.sim import make_env, replay, replay_from
from bpp.cli import main as bpp
from bpp.data.store import EpisodeStore


def replay_in_file(env, seed: int, states, actions, fixtures) -> tuple[np.ndarray, bool]:
    """:func:`replay`, in the scene the demonstration's exported ``model_file`` compiles."""
    env.env.reset_from_xml_string(scene_xml(env, seed, fixtures))
    return replay_from(env, states[0], actions)


def replay_store(store: EpisodeStore, variant: str) -> list[dict]:
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
                if variant == "float32":
                    actions = actions.astype(np.float32).astype(np.float64)
                seed, fixtures = int(store.column("seed")[episode]), episode_fixtures(store, episode)
                run = replay_in_file if variant == "file" else replay
                states, success = run(envs[task], seed, steps["sim_state"], actions, fixtures)
                gap = np.abs(states[:-1] - steps["sim_state"]).max(axis=1)
                first = int(np.flatnonzero(gap)[0]) if gap.any() else None
                rows.append({"success": success, "exact": first is None, "final_gap": float(gap[-1]), "first": first})
        finally:
            for env in envs.values():
                env.close()
    return rows


def summary(label: str, rows: list[dict]) -> str:
    n = len(rows)
    success = sum(r["success"] for r in rows)
    exact = sum(r["exact"] for r in rows)
    gaps = np.array([r["final_gap"] for r in rows])
    first = [r["first"] for r in rows if r["first"] is not None]
    return (
        f"| {label} | {n} | {success} ({100 * success / n:.1f}%) | {exact} ({100 * exact / n:.1f}%) | "
        f"{np.median(gaps):.3g} | {gaps.max():.3g} | {min(first) if first else ''} |"
    )


LABELS = {"stored": "as stored", "float32": "rounded to float32", "file": "as stored, in its model_file's scene"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stores", type=Path, nargs="*")
    parser.add_argument("--generate", type=Path, help="first generate this store (flags below)")
    parser.add_argument("--suite", default="combination")
    parser.add_argument("--num-tasks", type=int, default=50)
    parser.add_argument("--task-indices", type=int, nargs="+", help="generate these training tasks (not --num-tasks)")
    parser.add_argument("--demos-per-task", type=int, default=2)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--variants", nargs="+", default=["stored", "float32"], choices=["stored", "float32", "file"])
    args = parser.parse_args()
    stores = list(args.stores)
    if args.generate:
        if not args.generate.exists():
            tasks = (
                ["--task-indices", *map(str, args.task_indices)]
                if args.task_indices
                else ["--num-tasks", str(args.num_tasks)]
            )
            bpp(["libero", "generate", "--out", str(args.generate), "--suite", args.suite, *tasks,
                 "--demos-per-task", str(args.demos_per_task), "--goal-size", "0",
                 "--workers", str(args.workers)])  # fmt: skip
        stores.append(args.generate)
    columns = ["actions replayed", "demonstrations", "reached the goal", "states bit for bit", "final gap: median"]
    print("| " + " | ".join([*columns, "max", "first step off"]) + " |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for path in stores:
        store = EpisodeStore(path)
        for variant in args.variants:
            t0 = time.perf_counter()
            rows = replay_store(store, variant)
            label = f"{path.name}: {LABELS[variant]}"
            print(summary(label, rows), f"<!-- {time.perf_counter() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
