"""Where one training step's time goes, part by part, on the device `bpp train` would use.

    python bench/gpu_step_profile.py                       # paper (batch 128) and cpu-image (batch 256) on a GPU
    python bench/gpu_step_profile.py --small               # toy sizes, to check the script on a CPU

For a batch already on the device, the step of `bpp.train.train_step` is split into its parts (task context
encoding, observation conditioning, diffusion loss, backward, clipping + AdamW, EMA); each part is timed twice:
the host's time to issue it (no waiting), and its time to completion (waiting for the device before and after).
Where issuing takes as long as completing, the step is bound by Python and kernel launches, not by the GPU.
Then torch.profiler's table of the operators that take the most host time over a few whole steps.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bpp.benchmarks.draw import dataset as draw_data
from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, _ema_update, build_training, uses_amp
from bpp.utils import to_torch

PRESETS = {"paper": ("paper", "paper", 128), "cpu-image": ("cpu", "image64", 256)}


def parts(model, ema, optimizer, batch, cfg, amp, device):
    """The step's parts in order, as (name, callable); state flows through `state`."""
    state = {}
    generator = torch.Generator(device).manual_seed(0)

    def autocast():
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp)

    def context():
        with autocast():
            ctx = model.encode_context(batch["context"])
            state["ctx"] = model.select_context(ctx, batch["context_index"])

    def condition():
        with autocast():
            state["cond"], _ = model.condition(batch["obs"], state["ctx"])

    def loss():
        with autocast():
            actions = model.normalize_actions(batch["action"], model.action_origin(batch["obs"]))
            state["loss"] = model.head.loss(actions, state["cond"], generator)

    def backward():
        optimizer.zero_grad(set_to_none=True)
        state["loss"].backward()

    def step():
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()

    def average():
        _ema_update(ema, model, 0.999)

    return [("context", context), ("condition", condition), ("loss", loss), ("backward", backward)] + [
        ("clip+adamw", step),
        ("ema", average),
    ]


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def profile(name: str, store: EpisodeStore, device: torch.device, small: bool, repeats: int) -> None:
    size, obs, batch_size = PRESETS[name]
    method = get_method("bpp")
    model_cfg = method.config("debug" if small else size, obs, BENCHMARK)
    if small:
        model_cfg, batch_size = replace(model_cfg, obs=replace(model_cfg.obs, image_size=32)), 8
    cfg = TrainConfig(data=store.path, batch_size=batch_size)
    model, ema, optimizer = build_training(cfg, method.model_cls(model_cfg, store.stats), device)
    model.train()
    batch = to_torch(
        PromptBatchDataset(store, model.data_spec(), frames=BENCHMARK.frames, batch_size=batch_size, seed=2)[0],
        device,
    )
    amp = uses_amp(cfg, device)
    steps = parts(model, ema, optimizer, batch, cfg, amp, device)
    issue = {n: [] for n, _ in steps}
    done = {n: [] for n, _ in steps}
    whole_issue, whole_done = [], []
    for r in range(repeats + 2):
        sync(device)
        t_start = time.perf_counter()
        for _, fn in steps:  # issued back to back, as in training
            fn()
        t_issued = time.perf_counter()
        sync(device)
        t_end = time.perf_counter()
        for n, fn in steps:  # each part alone, waiting before and after
            sync(device)
            t0 = time.perf_counter()
            fn()
            t1 = time.perf_counter()
            sync(device)
            t2 = time.perf_counter()
            if r >= 2:
                issue[n].append(t1 - t0)
                done[n].append(t2 - t0)
        if r >= 2:
            whole_issue.append(t_issued - t_start)
            whole_done.append(t_end - t_start)
    print(f"\n== {name}: batch {batch_size}, {sum(p.numel() for p in model.parameters()) / 1e6:.1f}M parameters")
    print(f"{'part':<12} {'issue ms':>9} {'done ms':>9}")
    for n, _ in steps:
        print(f"{n:<12} {1000 * np.median(issue[n]):9.1f} {1000 * np.median(done[n]):9.1f}")
    print(f"{'whole step':<12} {1000 * np.median(whole_issue):9.1f} {1000 * np.median(whole_done):9.1f}")
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(3):
            for _, fn in steps:
                fn()
        sync(device)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))
    if device.type == "cuda":
        print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=15, max_name_column_width=60))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--small", action="store_true")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-gpu"))
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    tasks = 6 if args.small else 40
    path = args.data_dir / f"profile-{tasks}.zarr"
    if not (path / "zarr.json").exists():
        cfg = replace(draw_data.PRESETS["cpu"], num_tasks=tasks, demos_per_task=5)
        draw_data.generate(cfg, path, overwrite=True, progress=False)
    store = EpisodeStore(path)
    for name in args.presets:
        profile(name, store, device, args.small, 2 if args.small else args.repeats)


if __name__ == "__main__":
    main()
