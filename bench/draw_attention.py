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
10-step chunks come in a random order, which a policy that finds its place by the chunks' content follows; with
``--rollout-memory K`` ICRT sees only its last K rollout chunks, its own included (what the rollout so far gives it).
"""

from __future__ import annotations

import argparse
import json
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
    parser.add_argument("--rollout-memory", type=int, default=0, help="ICRT: rollout chunks an inference sees (0: all)")
    parser.add_argument("--scores", type=Path, help="where to write each rollout's score (JSON), to pair runs")
    args = parser.parse_args()
    ckpt, benchmark, task_set, tasks = evaluated_tasks(args)
    store = task_set.store
    protocol = Protocol(rollouts=args.rollouts, prompts=args.prompts)
    rows = [(task, row) for task in tasks for row in protocol.plan(store, task, benchmark)]
    plan, task_of = [row for _, row in rows], np.array([task for task, _ in rows])
    model = ckpt.build_model()
    if args.rollout_memory:
        if not hasattr(model, "limit_rollout_memory"):
            raise SystemExit(f"{args.run}: --rollout-memory is ICRT's (this run is {NAMES[ckpt.method]})")
        model.limit_rollout_memory(args.rollout_memory)
    agent = PolicyAgent(model, record_attention=True, **protocol.agent_options())
    results, attention = run_prompted(agent, benchmark, store, plan, benchmark.max_steps, [False] * len(plan))
    if attention is None:
        raise SystemExit(f"{args.run}: this method reports no prompt attention")
    cfg = agent.model.cfg
    if hasattr(cfg, "prompt"):  # BPP: column 0 is its attention sinks' mass
        chunk_len, rest = cfg.prompt.chunk_len, "the attention sinks'"
    else:  # ICRT: column 0 is its rollout's
        chunk_len, rest = cfg.chunk_len, "its own rollout's"
    measures = []
    for row, maps in zip(plan, attention, strict=True):
        sl = store.episode_slice(int(row["prompt_episode"]))
        measures.append(rollout_attention(maps, sl.stop - sl.start, chunk_len, agent.n_action_steps))
    scores = np.array([r.score for r in results])
    memory = f", rollout memory {args.rollout_memory} chunks" if args.rollout_memory else ""
    by_task = [scores[task_of == t].mean() for t in tasks]
    sem = np.std(by_task, ddof=1) / np.sqrt(len(tasks))
    print(f"{len(plan)} rollouts ({args.prompts} prompts{memory}) of {len(tasks)} tasks: "
          f"mean score {scores.mean():.2f} ± {sem:.2f} px (s.e.m. over tasks)")  # fmt: skip
    if args.scores:
        args.scores.parent.mkdir(parents=True, exist_ok=True)
        args.scores.write_text(
            json.dumps([{"task": int(t), "score": float(x)} for t, x in zip(task_of, scores, strict=True)])
        )
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
