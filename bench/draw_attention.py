"""Where a policy's observation looks in its prompt as a rollout goes on: does its attention walk through the
prompt's chunks in step with the drawing?

    python bench/draw_attention.py runs/demo-bpp --num-tasks 50 --rollouts 2 --figure docs/figures/draw_attention.png
    python bench/draw_attention.py runs/icrt --num-tasks 50 --rollouts 2      # ICRT: its observation token's attention

The unseen drawings' rollouts under `bpp eval`'s protocol (in this process, one batch), each inference's attention
over the prompt, as the model reports it (averaged over layers and heads). Apart from the prompt's chunks, BPP
reports its attention sinks' mass, ICRT the mass on its own rollout so far (its earlier chunks' tokens). Per
rollout and inference: the centre of the attention's mass over the prompt's chunks (0: its first chunk's middle,
1: its last's) against the inference's place in time (its first step over the prompt's length, 1 and beyond once
the rollout has taken as many steps as the prompt). Printed over rollouts: Spearman's rank correlation of the centre
with the inference's index, the mean distance of the centre from the place in time, the mass on the most attended
chunk against an even spread's, and the rest's share (sinks or rollout); with ``--prompts shuffled`` the prompt's
10-step chunks come in a random order, which a policy that finds its place by the chunks' content follows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np
from scipy import stats

from bpp.core.prompting import run_prompted
from bpp.evaluation.protocol import Protocol
from bpp.policies.agent import PolicyAgent
from common import NAMES, add_eval_arguments, evaluated_tasks

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def rollout_attention(attention: np.ndarray, prompt_steps: int, chunk_len: int, n_action_steps: int) -> dict:
    """One rollout's measures from its (calls, 1 + chunks) attention (column 0: the sinks, or the rollout so far)."""
    chunks = -(-prompt_steps // chunk_len)
    on_chunks = attention[:, 1 : 1 + chunks]
    weights = on_chunks / np.maximum(on_chunks.sum(axis=1, keepdims=True), 1e-12)
    centre = weights @ np.arange(chunks) / max(chunks - 1, 1)
    time = np.arange(len(attention)) * n_action_steps / prompt_steps
    return {
        "centre": centre,
        "time": time,
        "rho": stats.spearmanr(np.arange(len(centre)), centre).statistic if len(centre) > 2 else np.nan,
        "lag": float(np.mean(np.abs(centre - np.minimum(time, 1.0)))),
        "peak": float(weights.max(axis=1).mean() * chunks),
        "rest": float(attention[:, 0].mean()),
    }


def mean_sem(values) -> str:
    values = np.asarray([v for v in values if np.isfinite(v)])
    return f"{values.mean():.2f} ± {values.std(ddof=1) / np.sqrt(len(values)):.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_eval_arguments(parser, num_tasks=50, rollouts=2)
    parser.add_argument("--prompts", default="own", choices=["own", "shuffled"])
    parser.add_argument("--figure", type=Path, help="where to draw each rollout's attention centre over time")
    args = parser.parse_args()
    ckpt, benchmark, task_set, tasks = evaluated_tasks(args)
    store = task_set.store
    protocol = Protocol(rollouts=args.rollouts, prompts=args.prompts)
    plan = [row for task in tasks for row in protocol.plan(store, task, benchmark)]
    agent = PolicyAgent(ckpt.build_model(), record_attention=True, **protocol.agent_options())
    results, attention = run_prompted(agent, benchmark, store, plan, benchmark.max_steps, [False] * len(plan))
    if attention is None:
        raise SystemExit(f"{args.run}: this method reports no prompt attention")
    cfg = agent.model.cfg
    chunk_len = cfg.prompt.chunk_len if hasattr(cfg, "prompt") else cfg.chunk_len
    rest = "the attention sinks'" if hasattr(cfg, "prompt") else "its own rollout's"
    measures = []
    for row, maps in zip(plan, attention, strict=True):
        sl = store.episode_slice(int(row["prompt_episode"]))
        measures.append(rollout_attention(maps, sl.stop - sl.start, chunk_len, agent.n_action_steps))
    scores = [r.score for r in results]
    print(f"{len(plan)} rollouts ({args.prompts} prompts) of {len(tasks)} tasks: mean score {np.mean(scores):.2f} px")
    print(f"Spearman's rho of the attention's centre with the inference's index: {mean_sem(m['rho'] for m in measures)}"
          f" (above 0.5 in {np.mean([m['rho'] > 0.5 for m in measures]):.0%} of rollouts)")  # fmt: skip
    print(f"distance of the centre from the place in time (0-1): {mean_sem(m['lag'] for m in measures)}")
    print(f"mass on the most attended chunk, in even spreads: {mean_sem(m['peak'] for m in measures)}")
    print(f"{rest} share of the attention: {mean_sem(m['rest'] for m in measures)}")
    if args.figure:
        fig, ax = plt.subplots(figsize=(4.6, 4.0))
        for m in measures:
            ax.plot(m["time"], m["centre"], color="tab:blue", alpha=0.25, linewidth=0.8)
        ax.plot([0, 1], [0, 1], color="black", linestyle="--", linewidth=1)
        ax.set_xlabel("inference's place in time (its step / the prompt's length)")
        ax.set_ylabel("attention's centre (0: first chunk, 1: last)")
        ax.set_title(
            f"{NAMES[ckpt.method]}'s prompt attention, {len(plan)} rollouts ({args.prompts} prompts)", fontsize=9
        )
        fig.tight_layout()
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=120)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
