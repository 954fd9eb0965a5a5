"""The scripted demonstrator from an evaluation's own initial states: how often does the demonstrator a policy imitates
succeed where the policy was judged? A policy's failures on states where the demonstrator fails too are a ceiling of
the data, not of learning.

    python bench/libero_demo_ceiling.py outputs/libero/one-task-150-near-abs-v2-8k-val \\
        data/libero/one-task-150-near-abs-v2.zarr

For every rollout of the evaluation (its task and ``init_seed``), the demonstrator of the store's configuration (its
rim side; without action noise unless ``--noise``) demonstrates the task once from that initial state (its own draws
seeded by ``init_seed`` too), and LIBERO's predicate judges it. Prints, per rollout, the policy's result and the
demonstrator's, and the two success counts side by side. Generated tasks only: LIBERO's own tasks start from its
initial-state files, which the demonstrator does not load.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.dataset import LiberoDataConfig, problem_text, task_id
from bpp.benchmarks.libero.demonstrator import DemoConfig, demonstrate_task
from bpp.benchmarks.libero.sim import make_env
from bpp.data.store import EpisodeStore
from bpp.utils import read_json


def data_config(store: EpisodeStore) -> LiberoDataConfig:
    """The generation configuration a store records (its lists back to the tuples the dataclasses hold)."""
    conf = dict(store.config)
    demo = {k: tuple(v) if isinstance(v, list) else v for k, v in conf.pop("demo").items()}
    fields = {f.name for f in dataclasses.fields(LiberoDataConfig)}
    conf = {k: tuple(v) if isinstance(v, list) else v for k, v in conf.items() if k in fields}
    return LiberoDataConfig(**conf, demo=DemoConfig(**demo))


def demonstrator_for(store: EpisodeStore, noise: float) -> tuple[LiberoDataConfig, DemoConfig, dict]:
    """The store's generation configuration, its demonstrator's settings with action noise `noise`, and its tasks by
    id; a store of LIBERO's own tasks is refused (ValueError): they start from its initial-state files, which the
    demonstrator does not load."""
    if any(task["info"].get("initial_states") for task in store.tasks):
        raise ValueError(f"{store.path} holds LIBERO's own tasks, which start from its initial-state files")
    cfg = data_config(store)
    tasks = {task_id(cfg.split, index, task): task for index, task in cfg.tasks()}
    return cfg, dataclasses.replace(cfg.demo, action_noise=noise), tasks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="an evaluation's output folder (its results.json)")
    parser.add_argument("store", type=Path, help="the store the policy was trained on (its demonstrator settings)")
    parser.add_argument("--noise", type=float, default=0.0, help="the demonstrator's action noise")
    args = parser.parse_args()
    results = read_json(args.results / "results.json")
    store = EpisodeStore(args.store)
    try:
        cfg, demo_cfg, tasks = demonstrator_for(store, args.noise)
    except ValueError as error:
        parser.error(str(error))
    policy, demos = [], []
    with tempfile.TemporaryDirectory(prefix="libero-ceiling-") as folder:
        envs = {}
        for row in results["rollouts"]:
            name = row["task_id"]
            if name not in envs:
                problem = Path(folder) / f"{name}.bddl"
                problem.write_text(problem_text(tasks[name], cfg.original))
                envs[name] = make_env(problem, render=False)
            demo = demonstrate_task(envs[name], tasks[name], int(row["init_seed"]), demo_cfg)
            policy.append(row["score"] >= 1.0)
            demos.append(bool(demo.success))
            print(
                f"{name} rollout {row['rollout']:3d} init {row['init_seed']:>10d}: policy "
                f"{'success' if policy[-1] else 'FAIL   '}  demonstrator {'success' if demos[-1] else 'FAIL'}"
            )
        for env in envs.values():
            env.close()
    policy, demos = np.array(policy), np.array(demos)
    print(f"\npolicy {policy.sum()}/{len(policy)}; demonstrator {demos.sum()}/{len(demos)}")
    print(f"where the policy failed, the demonstrator succeeded {demos[~policy].sum()} of {(~policy).sum()} times")
    print(f"where the demonstrator failed, the policy succeeded {policy[~demos].sum()} of {(~demos).sum()} times")


if __name__ == "__main__":
    main()
