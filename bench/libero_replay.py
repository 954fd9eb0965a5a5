"""A trained LIBERO-Gen policy run from the exact initial state of one of its training demonstrations, its gripper's
path compared with the demonstration's step by step: does it reproduce what it was trained on, and where does it
leave it?

    python bench/libero_replay.py runs/libero_overfit/bpp data/libero/combination-5x8.zarr --episodes 0 8

The policy is prompted with another demonstration of the same task (as in training). Printed per episode: the first
action against the demonstration's, a row every --every steps (gripper position, its offset from the
demonstration's at the same step, both actions), the step at which the gripper first closes in each, how far apart
they are then, and the outcome by LIBERO's predicate.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from bpp.benchmarks.libero.dataset import ABSOLUTE_KEY, PROPRIO_LAYOUT
from bpp.benchmarks.libero.demonstrator import SETTLE_STEPS
from bpp.benchmarks.libero.rollouts import observe, task_problem
from bpp.benchmarks.libero.sim import delta_actions, make_env, reset_env
from bpp.checkpoint import Checkpoint
from bpp.core.registry import get_benchmark
from bpp.data.contexts import task_context
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent

EEF = list(PROPRIO_LAYOUT["eef_pos"])
"""The gripper's position in LIBERO's proprioception."""


def replay(model, store: EpisodeStore, episode: int, every: int, max_steps: int) -> None:
    benchmark = get_benchmark(store.benchmark)
    tasks = store.column("task_index")
    prompt = next(int(e) for e in np.flatnonzero(tasks == tasks[episode]) if e != episode)
    agent = PolicyAgent(model)
    agent.reset(task_context(store, prompt, agent.data_spec, benchmark.frames), seed=0)
    demo = store.episode(episode, ["proprio", "action"])
    n = len(demo["action"])
    closes = {"demo": int(np.argmax(demo["action"][:, -1] > 0)), "policy": None}
    print(f"## episode {episode} ({store.tasks[int(tasks[episode])]['id']}, {n} steps), prompt {prompt}")
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "task.bddl"
        path.write_text(task_problem(store, episode))
        env = make_env(path)
        try:
            raw = reset_env(env, int(store.column("seed")[episode]))
            for _ in range(SETTLE_STEPS):  # as generation and evaluation start
                raw, *_ = env.step(np.zeros(7))
            obs = observe(env, raw, (), 0)
            start = np.abs(obs["proprio"] - demo["proprio"][0]).max()
            print(f"start: the observation differs from the demonstration's by at most {start:.2g}")
            path_eef = []
            for t in range(min(n + 100, max_steps)):
                action = agent.act({k: obs[k] for k in agent.obs_keys})
                path_eef.append(obs["proprio"][EEF].copy())
                if closes["policy"] is None and action[-1] > 0:
                    closes["policy"] = t
                if t % every == 0:
                    k = min(t, n - 1)
                    offset = obs["proprio"][EEF] - demo["proprio"][k][EEF]
                    print(
                        f"t={t:3d} gripper {np.round(obs['proprio'][EEF], 3)} offset {np.round(offset, 3)} "
                        f"action {np.round(action, 2)} demo {np.round(demo['action'][k], 2)}"
                    )
                if agent.data_spec.action_key == ABSOLUTE_KEY:  # a position goal: the delta from where the gripper is
                    action = delta_actions(action, raw["robot0_eef_pos"])
                raw, *_ = env.step(np.clip(action, -1.0, 1.0))
                obs = observe(env, raw, (), 0)
                if env.env._check_success():
                    print(f"success at step {t}")
                    break
            else:
                print("no success")
        finally:
            env.close()
    c = closes["policy"]
    if c is None:
        print(f"the demonstration closes its gripper at step {closes['demo']}; the policy never does")
    else:
        apart = np.linalg.norm(path_eef[c] - demo["proprio"][closes["demo"]][EEF])
        print(
            f"the demonstration closes its gripper at step {closes['demo']}, the policy first at step {c}, "
            f"{100 * apart:.1f} cm from where the demonstration closed it"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("store", type=Path, help="the store the run was trained on")
    parser.add_argument("--episodes", type=int, nargs="+", default=[0])
    parser.add_argument("--every", type=int, default=10, help="print a row every this many steps")
    parser.add_argument("--max-steps", type=int, default=550)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = Checkpoint.load(args.run, use_ema=True).build_model()
    store = EpisodeStore(args.store)
    for episode in args.episodes:
        replay(model, store, episode, args.every, args.max_steps)


if __name__ == "__main__":
    main()
