"""What does a trained diffusion policy actually condition on? A probe on held-out training-style windows.

    python bench/conditioning_probe.py runs/bpp-cpu --store data/draw/val.zarr

For a diffusion-decoder checkpoint (BPP, Goal-Image, Language) and B windows drawn as in training (several tasks per
batch, each with its own context), it reports

* the noise-prediction error at fixed diffusion steps k with (a) the real inputs, (b) the observation history
  without motion (every history step replaced by the current one, so the cursor's velocity is gone) and (c) each
  sample given another task's context. If (b) or (c) barely moves the error, the model ignores that input;
* sampled action chunks against the demonstrations': the error of the first executed action and of all executed
  actions (px at 512; board-frame units x 350 px), next to the error of a policy that puts its first action at the
  right distance from the cursor in a uniformly random direction (4/pi times that distance).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from bpp.checkpoint import load_policy
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.utils import to_torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("--store", required=True, help="windows come from this store (e.g. a validation split)")
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--tasks-per-batch", type=int, default=8)
    parser.add_argument("--px-per-unit", type=float, default=350.0, help="1.0 for canvas actions, 350 for board")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_policy(args.run, "cpu", True).eval()
    ds = PromptBatchDataset(args.store, model.data_spec(), batch_size=64, seed=5, tasks_per_batch=args.tasks_per_batch)
    head, Ta, start = model.head, model.cfg.horizons.n_action_steps, model.cfg.horizons.n_obs_steps - 1
    losses: dict[str, dict[int, list[float]]] = {n: {} for n in ("real", "no motion", "other task's context")}
    first, executed, lead = [], [], []
    for i in range(args.batches):
        batch = to_torch(ds[i], "cpu")
        still = {k: v[:, -1:].expand_as(v).contiguous() for k, v in batch["obs"].items()}
        other = dict(batch, context_index=(batch["context_index"] + 1) % args.tasks_per_batch)
        target = model.normalize_actions(batch["action"], model.action_origin(batch["obs"]))
        with torch.no_grad():
            for name, b in (("real", batch), ("no motion", dict(batch, obs=still)), ("other task's context", other)):
                ctx = model.select_context(model.encode_context(b["context"]), b["context_index"])
                cond, _ = model.condition(b["obs"], ctx)
                g = torch.Generator().manual_seed(i)
                for k in (10, 50, 90):
                    noise = torch.randn(target.shape, generator=g)
                    ks = torch.full((target.shape[0],), k)
                    eps = head.net(head.train_scheduler.add_noise(target, noise, ks), ks, cond)
                    losses[name].setdefault(k, []).append(torch.nn.functional.mse_loss(eps, noise).item())
            ctx = model.select_context(model.encode_context(batch["context"]), batch["context_index"])
            sampled = model.predict_action(batch["obs"], ctx, generator=torch.Generator().manual_seed(i))["action"]
        truth = batch["action"][:, start : start + Ta, :2]
        pred = sampled[:, start : start + Ta, :2]
        first.append((pred[:, 0] - truth[:, 0]).norm(dim=-1).mean().item())
        executed.append((pred - truth).norm(dim=-1).mean().item())
        cursor = batch["obs"][model.cfg.obs.proprio_keys[0]][:, -1, :2]  # the position key (same frame as actions)
        lead.append((truth[:, 0] - cursor).norm(dim=-1).mean().item())
    px = args.px_per_unit
    print(f"{args.run}: noise-prediction error (MSE) at diffusion step k")
    for name, by_k in losses.items():
        print(f"  {name:22s} " + "  ".join(f"k={k}: {np.mean(v):.4f}" for k, v in by_k.items()))
    print(f"  first executed action error  {np.mean(first) * px:6.1f} px")
    print(f"  all {Ta} executed actions    {np.mean(executed) * px:6.1f} px")
    print(f"  first action's distance from the cursor {np.mean(lead) * px:6.1f} px; a random direction at that")
    print(f"  distance would err by about {4 / math.pi * np.mean(lead) * px:6.1f} px")


if __name__ == "__main__":
    main()
