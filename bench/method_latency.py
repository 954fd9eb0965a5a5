"""Inference latency of every method on this CPU, measured over whole 400-step DrawAnything rollouts.

    python bench/method_latency.py --data data/draw/cpu.zarr --preset cpu [--obs canvas] \\
        [--methods bpp goal_image icrt language]

For each method, at size preset `--preset` observing DrawAnything's observation preset `--obs` (default: the
benchmark's own for that size, `canvas` state for `cpu` and the 224x224 camera for `paper`), with untrained weights
(latency does not depend on training): `reset` (the task context is encoded once per rollout) and then `act` for
400 steps of a real env rollout with early stopping off. Reported: the latency of the `act` calls that run the
network (p50 / p95), the per-step cost amortised over all 400 `act` calls, and, for ICRT, how the latency of a
network call grows with the rollout history (its KV cache grows by two tokens per chunk). Language runs once per
``--text-encoders`` choice, on a store whose tasks carry instructions (``--language-data``, e.g. written by
``bpp draw generate --describe``).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.env import ACTION_FRAMES, DrawEnv
from bpp.data.contexts import task_context
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method


def rollout_timings(agent: PolicyAgent, store: EpisodeStore, steps: int) -> tuple[float, list[tuple[int, float]]]:
    """(reset seconds, [(step, act seconds)]) over one rollout of `steps` steps."""
    spec = agent.data_spec
    env = DrawEnv(
        image_size=spec.image_size if spec.image_keys else None,
        early_stop=False,
        max_episode_steps=steps,
        action_frame=ACTION_FRAMES[spec.action_key],
    )
    obs, _ = env.reset(seed=0, options={"board_angle": 0.3})
    t0 = time.perf_counter()
    agent.reset(task_context(store, 0, spec, BENCHMARK.frames), seed=0)
    reset_s = time.perf_counter() - t0
    times = []
    for step in range(steps):
        t0 = time.perf_counter()
        action = agent.act(obs)
        times.append((step, time.perf_counter() - t0))
        obs, *_ = env.step(action)
    return reset_s, times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data/draw/cpu.zarr")
    parser.add_argument("--preset", default="cpu", help="size preset, the same for every method")
    parser.add_argument(
        "--obs", default=None, help="DrawAnything observation preset (default: the benchmark's own for the size)"
    )
    parser.add_argument("--methods", nargs="+", default=["bpp", "goal_image", "icrt"])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--language-data", default="", help="a store with instructions (for --methods language)")
    parser.add_argument("--text-encoders", nargs="+", default=["scratch", "pretrained"], help="Language's encoders")
    args = parser.parse_args()
    store = language_store = EpisodeStore(args.data)
    runs = [(name, None) for name in args.methods if name != "language"]
    if "language" in args.methods:
        if not args.language_data:
            parser.error("--methods language needs --language-data: a store made with `bpp draw generate --describe`")
        language_store = EpisodeStore(args.language_data)
        runs += [("language", encoder) for encoder in args.text_encoders]
    preset = args.preset if args.obs is None else f"{args.preset}, observations {args.obs}"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, preset {preset}")
    header = "| method | params | reset (context encoding) | network call p50 / p95 | calls | per step, amortised |"
    print("\n" + header + "\n| --- | ---: | ---: | ---: | ---: | ---: |")
    growth = {}
    for name, text_encoder in runs:
        method = get_method(name)
        cfg, label, data = method.config(args.preset, args.obs, BENCHMARK), name, store
        if text_encoder is not None:
            cfg = replace(cfg, text_encoder=text_encoder, tokenizer="pretrained")
            label, data = f"{name} ({text_encoder} text encoder)", language_store
        torch.manual_seed(0)
        model = method.model_cls(cfg, data.stats).eval()
        agent = PolicyAgent(model)
        rollout_timings(agent, data, 24)  # warm-up
        reset_s, times = rollout_timings(agent, data, args.steps)
        every = agent.n_action_steps
        calls = np.array([t for step, t in times if step % every == 0]) * 1e3
        total = sum(t for _, t in times) * 1e3
        params = sum(p.numel() for p in model.parameters()) / 1e6
        print(
            f"| {label} | {params:.1f}M | {reset_s * 1e3:.1f} ms | {np.percentile(calls, 50):.1f} / "
            f"{np.percentile(calls, 95):.1f} ms | {len(calls)} | {total / len(times):.2f} ms |"
        )
        if name == "icrt":
            growth[name] = [(step, t * 1e3) for step, t in times if step % every == 0]
    for name, rows in growth.items():
        marks = [rows[i] for i in np.unique(np.linspace(0, len(rows) - 1, 6).round().astype(int))]
        print(f"\n{name}: network call latency along the rollout (history grows): ")
        print("  " + ", ".join(f"step {step}: {ms:.1f} ms" for step, ms in marks))
        first, last = np.median([ms for _, ms in rows[:5]]), np.median([ms for _, ms in rows[-5:]])
        print(f"  median of the last 5 calls / first 5 calls: {last / first:.2f}")


if __name__ == "__main__":
    main()
