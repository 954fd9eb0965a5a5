"""BPP inference latency and training / data-loading throughput on this machine.

    python bench/bpp_latency.py --data data/draw/cpu.zarr [--presets cpu paper] [--obs canvas] [--calls 30]

For each BPP size preset, observing DrawAnything's observation preset `--obs` (default: the benchmark's own for that
size, `canvas` state for `cpu` and the 224x224 camera for `paper`): the latency of one inference call of
``PolicyAgent`` (prompt encoder once + all DDIM steps; ``act`` runs it every Ta steps, the other ``act`` calls only
pop the action queue) with a 100-step and an 800-step prompt (the prompt itself is encoded once at ``reset``,
outside the timing), the 800/100 ratio, then training samples/s and data-loader samples/s (one worker process).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.data.contexts import task_context
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.model import BPPModel
from bpp.policies.registry import get_method
from bpp.utils import to_torch


def _prompt_of_length(store, model, steps: int) -> dict:
    base = task_context(store, 0, model.data_spec(), BENCHMARK.frames)
    reps = -(-steps // len(base["action"]))
    return {
        "obs": {k: np.concatenate([v] * reps)[:steps] for k, v in base["obs"].items()},
        "action": np.concatenate([base["action"]] * reps)[:steps],
    }


def act_latency(store, model, prompt_steps: int, calls: int) -> np.ndarray:
    agent = PolicyAgent(model)
    agent.reset(_prompt_of_length(store, model, prompt_steps), seed=0)
    ep = task_context(store, 1, model.data_spec(), BENCHMARK.frames)
    obs = {k: v[0] for k, v in ep["obs"].items()}
    agent.act(obs)  # warm-up
    times = []
    for _ in range(calls):
        agent.queue.clear()  # force an inference call
        t0 = time.perf_counter()
        agent.act(obs)
        times.append(time.perf_counter() - t0)
    return np.array(times) * 1e3


def train_rate(store, model, batch_size: int, steps: int) -> float:
    ds = _dataset(store, model, batch_size)
    batches = [to_torch(ds[i], "cpu") for i in range(steps + 1)]
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    model.train()

    def step(b):
        loss = model(b)
        opt.zero_grad()
        loss.backward()
        opt.step()

    step(batches[0])
    t0 = time.perf_counter()
    for b in batches[1:]:
        step(b)
    return steps * batch_size / (time.perf_counter() - t0)


def _dataset(store, model, batch_size):
    return PromptBatchDataset(store, model.data_spec(), batch_size=batch_size, seed=1)


def loader_rate(store, model, batch_size: int, batches: int) -> float:
    ds = _dataset(store, model, batch_size)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, sampler=range(batches), num_workers=1)
    it = iter(loader)
    next(it)  # worker start-up
    t0 = time.perf_counter()
    n = sum(1 for _ in it)
    return n * batch_size / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data/draw/cpu.zarr")
    parser.add_argument("--presets", nargs="+", default=["cpu", "paper"], help="BPP size presets")
    parser.add_argument(
        "--obs", default=None, help="DrawAnything observation preset (default: the benchmark's own for each size)"
    )
    parser.add_argument("--calls", type=int, default=30)
    args = parser.parse_args()
    store = EpisodeStore(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    for name in args.presets:
        cfg = get_method("bpp").config(name, args.obs, BENCHMARK)
        torch.manual_seed(0)
        model = BPPModel(cfg, store.stats).eval()
        params = sum(p.numel() for p in model.parameters()) / 1e6
        short = act_latency(store, model, 100, args.calls)
        long = act_latency(store, model, 800, args.calls)
        ta = cfg.horizons.n_action_steps
        title = name if args.obs is None else f"{name}, {args.obs}"
        print(f"\n[{title}] {params:.1f}M params, {cfg.diffusion.num_inference_steps} DDIM steps, Ta={ta}")
        for label, t in (("100-step prompt", short), ("800-step prompt", long)):
            print(
                f"  inference call, {label}: p50 {np.percentile(t, 50):.1f} ms, p95 {np.percentile(t, 95):.1f} ms"
                f"  (per act, amortised over Ta: {np.percentile(t, 50) / ta:.1f} ms)"
            )
        print(f"  latency ratio 800/100 (p50): {np.median(long) / np.median(short):.3f}")
        bs = 64 if name != "paper" else 8
        steps = 20 if name != "paper" else 3
        tr = train_rate(store, model, bs, steps)
        lr = loader_rate(store, model, bs, 40 if name != "paper" else 6)
        print(
            f"  training: {tr:.0f} samples/s (batch {bs}); data loader (1 worker): {lr:.0f} samples/s "
            f"= {lr / tr:.1f}x what training consumes"
        )


if __name__ == "__main__":
    main()
