"""BPP inference latency and training / data-loading throughput on this machine.

    python bench/bpp_latency.py --data data/draw/cpu.zarr [--presets cpu paper] [--calls 30]

For each preset: the latency of one inference call of ``PolicyAgent`` (prompt encoder once + all DDIM steps;
``act`` runs it every Ta steps, the other ``act`` calls only pop the action queue) with a 100-step and an
800-step prompt (the prompt itself is encoded once at ``reset``, outside the timing), the 800/100 ratio, then
training samples/s and data-loader samples/s (one worker process).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
import torch
from bpp.evaluation.draw import prompt_from_store

from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.config import PRESETS
from bpp.policies.bpp.model import BPPModel
from bpp.utils import to_torch


def _prompt_of_length(store, model, steps: int) -> dict:
    cfg = model.cfg.obs
    keys = [*cfg.image_keys, *cfg.lowdim_keys, *cfg.proprio_keys]
    base = prompt_from_store(store, 0, keys, cfg.image_keys, cfg.image_size)
    reps = -(-steps // len(base["action"]))
    return {
        "obs": {k: np.concatenate([v] * reps)[:steps] for k, v in base["obs"].items()},
        "action": np.concatenate([base["action"]] * reps)[:steps],
    }


def act_latency(store, model, prompt_steps: int, calls: int) -> np.ndarray:
    agent = PolicyAgent(model)
    agent.reset(_prompt_of_length(store, model, prompt_steps), seed=0)
    ep = prompt_from_store(store, 1, model.obs_keys(), model.cfg.obs.image_keys, model.cfg.obs.image_size)
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
    parser.add_argument("--presets", nargs="+", default=["cpu", "paper"])
    parser.add_argument("--calls", type=int, default=30)
    args = parser.parse_args()
    store = EpisodeStore(args.data)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    for name in args.presets:
        cfg = PRESETS[name]
        if name == "paper":
            cfg = replace(cfg, obs=replace(cfg.obs, image_keys=("image",)))
        torch.manual_seed(0)
        model = BPPModel(cfg, store.stats).eval()
        params = sum(p.numel() for p in model.parameters()) / 1e6
        short = act_latency(store, model, 100, args.calls)
        long = act_latency(store, model, 800, args.calls)
        ta = cfg.horizons.n_action_steps
        print(f"\n[{name}] {params:.1f}M params, {cfg.diffusion.num_inference_steps} DDIM steps, Ta={ta}")
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
