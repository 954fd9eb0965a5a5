"""Teacher-forced action error of a trained policy on stored demonstrations, prompted by the episode's own task and
by another task: does the policy reproduce its training data, and does the prompt change what it does?

    python bench/open_loop.py runs/libero_cpu/bpp-s0 data/libero/combination-train.zarr --episodes 0 100 200

For each episode, the agent is reset with the context of another demonstration of the same task (then of a
demonstration of a different task) and fed the episode's stored observations step by step (no simulator); its
actions are compared with the stored ones: the mean absolute error per action dimension, and how often the
gripper command has the demonstration's sign. Any benchmark's store with an ``action`` column works.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from bpp.checkpoint import Checkpoint
from bpp.core.registry import get_benchmark
from bpp.data.contexts import task_context
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("store", type=Path)
    parser.add_argument("--episodes", type=int, nargs="+", default=[0, 100, 200])
    parser.add_argument("--steps", type=int, default=200, help="at most this many steps per episode")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    checkpoint = Checkpoint.load(args.run, use_ema=True)
    model = checkpoint.build_model()
    store = EpisodeStore(args.store)
    benchmark = get_benchmark(store.benchmark)
    tasks = store.column("task_index")[:]
    probe = PolicyAgent(model)
    spec, keys = probe.data_spec, probe.obs_keys
    print("| episode | steps | prompt | mean abs error per action dimension | gripper sign agrees |")
    print("| --- | --- | --- | --- | --- |")
    means: dict[str, list[np.ndarray]] = {"same task": [], "another task": []}
    for episode in args.episodes:
        same = [e for e in np.flatnonzero(tasks == tasks[episode]) if e != episode]
        if not same:
            print(f"| {episode} | - | - | its task has no other demonstration | - |")
            continue
        other = int(np.flatnonzero(tasks != tasks[episode])[episode % max(1, int((tasks != tasks[episode]).sum()))])
        rows = store.episode_slice(episode)
        actions = store[spec.action_key][rows][: args.steps]
        observations = {k: store[k][rows][: args.steps] for k in keys}
        for name, prompt in (("same task", int(same[0])), ("another task", other)):
            agent = PolicyAgent(model)
            agent.reset(task_context(store, prompt, spec, benchmark.frames), seed=0)
            predicted = np.array([agent.act({k: observations[k][t] for k in keys}) for t in range(len(actions))])
            error = np.abs(predicted - actions).mean(0)
            agrees = np.mean(np.sign(predicted[:, -1]) == np.sign(actions[:, -1]))
            errors = ", ".join(f"{e:.3f}" for e in error)
            print(f"| {episode} | {len(actions)} | {name} (episode {prompt}) | {errors} | {agrees:.2f} |")
            means[name].append(error)
    for name, errors in means.items():
        if errors:
            per_episode = np.stack(errors).mean(1)
            sem = per_episode.std(ddof=1) / np.sqrt(len(per_episode)) if len(per_episode) > 1 else float("nan")
            mean = per_episode.mean()
            print(f"{name}: mean abs error over {len(errors)} episodes and dimensions {mean:.4f} ± {sem:.4f}")


if __name__ == "__main__":
    main()
