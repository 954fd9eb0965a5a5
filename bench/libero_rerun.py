"""Chosen rollouts of a LIBERO-Gen evaluation run again, filmed: where does a policy go wrong on the initial states it
fails from, and what does the scripted demonstrator do from the same states?

    python bench/libero_rerun.py outputs/libero/one-task-150-near-abs-v2-12k-val \\
        data/libero/one-task-150-near-abs-v2.zarr --rollouts 4 19 20 --out outputs/bench/libero_rerun

Each chosen rollout (its position in the evaluation's ``results.json`` rollouts) starts from its own initial state
with its own prompt and sampling seed, as the evaluation ran it; its agent-view frames every --every steps go into one
contact sheet per rollout (``rollout_<i>.png``). With --demonstrator, the store's demonstrator (its settings, no
action noise) then demonstrates the task from the same initial state, filmed the same way (``demonstrator_<i>.png``).
Printed per rollout: each one's outcome and length, what the policy's rollout recorded (whether it lifted the right
object or another), and the step at which the demonstrator first closed its gripper.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from bpp.benchmarks.libero.dataset import problem_text
from bpp.benchmarks.libero.demonstrator import demonstrate_task
from bpp.benchmarks.libero.rollouts import VIDEO_STRIDE, run_rollouts
from bpp.benchmarks.libero.sim import make_env, render_states
from bpp.checkpoint import Checkpoint
from bpp.core.registry import get_benchmark
from bpp.data.contexts import task_context
from bpp.data.store import EpisodeStore
from bpp.media import contact_sheet
from bpp.policies.agent import PolicyAgent
from bpp.utils import read_json
from libero_demo_ceiling import demonstrator_for


def policy_rollout(
    agent: PolicyAgent, store: EpisodeStore, index: int, row: dict, every: int, size: int, columns: int, out: Path
) -> None:
    benchmark = get_benchmark(store.benchmark)
    context = task_context(store, int(row["prompt_episode"]), agent.data_spec, benchmark.frames)
    agent.reset(context, seed=int(row["seed"]))
    result = run_rollouts(agent, store, [row], record_frames=["all"], video_size=size)[0]
    # Frame i shows the scene after step i * VIDEO_STRIDE (0: the settled initial state); the last, the end.
    picked = list(range(0, len(result.frames) - 1, max(1, every // VIDEO_STRIDE)))
    frames = [result.frames[i] for i in picked] + [result.frames[-1]]
    steps = [i * VIDEO_STRIDE for i in picked] + [result.steps]
    verdict = f"{'success' if result.score >= 1 else 'failure'} in {result.steps} steps"
    title = f"policy, rollout {index} ({row['task_id']}): {verdict}"
    contact_sheet(frames, [f"step {s}" for s in steps], out / f"rollout_{index}.png", columns, title)
    print(f"rollout {index}: policy {verdict}; recorded {result.extra}")


def demonstrator_rollout(demonstrator, index: int, row: dict, every: int, size: int, columns: int, out: Path) -> None:
    cfg, demo_cfg, tasks = demonstrator
    task = tasks[row["task_id"]]
    with tempfile.TemporaryDirectory(prefix="libero-rerun-") as folder:
        problem = Path(folder) / "task.bddl"
        problem.write_text(problem_text(task, cfg.original))
        env = make_env(problem, render=True)
        try:
            demo = demonstrate_task(env, task, int(row["init_seed"]), demo_cfg)
            picked = list(range(0, len(demo.states), every))
            frames = list(render_states(env, demo.states[picked], "agentview", size))
        finally:
            env.close()
    closes = int(np.argmax(demo.actions[:, -1] > 0)) if (demo.actions[:, -1] > 0).any() else None
    verdict = "success" if demo.success else "failure"
    title = f"demonstrator, rollout {index}'s initial state: {verdict} in {len(demo.actions)} steps"
    contact_sheet(frames, [f"step {i}" for i in picked], out / f"demonstrator_{index}.png", columns, title)
    print(f"rollout {index}: demonstrator {verdict} in {len(demo.actions)} steps, closes at step {closes}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="an evaluation's output folder (its results.json)")
    parser.add_argument("store", type=Path, help="the store it evaluated on (its prompts)")
    parser.add_argument("--rollouts", type=int, nargs="+", required=True, help="positions in results.json's rollouts")
    parser.add_argument("--every", type=int, default=25, help="a frame every this many steps")
    parser.add_argument("--demonstrator", action="store_true", help="also film the demonstrator from each state")
    parser.add_argument("--size", type=int, default=128, help="frames' size (px)")
    parser.add_argument("--columns", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/libero_rerun"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = read_json(args.results / "results.json", "results file")
    store = EpisodeStore(args.store)
    demonstrator = None
    if args.demonstrator:
        try:
            demonstrator = demonstrator_for(store, noise=0.0)
        except ValueError as error:
            parser.error(str(error))
    agent = PolicyAgent(Checkpoint.load(results["checkpoint"], use_ema=True).build_model())
    args.out.mkdir(parents=True, exist_ok=True)
    rows = results["rollouts"]
    for index in args.rollouts:
        if not 0 <= index < len(rows):
            parser.error(f"--rollouts {index}: the evaluation has rollouts 0 to {len(rows) - 1}")
        policy_rollout(agent, store, index, rows[index], args.every, args.size, args.columns, args.out)
        if demonstrator is not None:
            demonstrator_rollout(demonstrator, index, rows[index], args.every, args.size, args.columns, args.out)


if __name__ == "__main__":
    main()
