"""What one training step costs a device, counted on a CPU: how many operators it dispatches, part by part (on a
GPU each is at least one kernel launch, and the host's time to issue them bounds a step of the small models:
BENCHMARKS.md, "Feeding a GPU"), and how many FLOPs it does per window sample and per task's prompt (what bounds the
large ones).

    python bench/step_ops.py                           # the paper and cpu-image architectures, on this CPU
    python bench/step_ops.py --presets paper --top 30  # and the 30 most frequent operators
    python bench/step_ops.py --measure flops           # the FLOPs alone

Operators: the count does not depend on the batch or image size, so the real architectures run here at batch 4 on
32x32 frames. Counted below autograd (``TorchDispatchMode``): forward, backward, clipping + AdamW (as on a GPU:
fused, one operator for all tensors), EMA; views (which launch nothing) are left out. With ``--amp`` the step runs
under CPU bf16 autocast, which adds the casts a GPU step makes under autocast (CPU and CUDA autocast differ in
details).

FLOPs (torch's ``FlopCounterMode``: matrix products, convolutions and attention, two FLOPs a multiply-add; norms
and pointwise operations are not counted, as in the usual utilisation figures): forward and backward of the
training loss at the preset's real image size, on a batch of 8 windows and on its first 4 with the same prompt. The
difference is 4 samples' cost; the rest is the prompt's, once per task per step. Clipping, AdamW and the EMA do no
such operation.
"""

from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from bpp.benchmarks.draw import dataset as draw_data
from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, _ema_update, build_training
from bpp.utils import to_torch
from common import step_flops

PRESETS = {"paper": ("paper", "paper"), "cpu-image": ("cpu", "image64"), "cpu-state": ("cpu", "board")}
TARGETS = {"paper": 2000, "cpu-image": 10000}  # the end-to-end targets on one GPU, samples/s


class OpCounter(TorchDispatchMode):
    """Counts the operators dispatched inside it (views left out), by name."""

    def __init__(self):
        super().__init__()
        self.counts = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not func.is_view and func.__name__ not in ("detach.default",):
            self.counts[func.__name__] += 1
        return func(*args, **(kwargs or {}))


def count(name: str, store: EpisodeStore, method_name: str, amp: bool, top: int) -> dict:
    size, obs = PRESETS[name]
    method = get_method(method_name)
    model_cfg = method.config(size, obs, BENCHMARK)
    if model_cfg.obs.image_keys:
        model_cfg = replace(model_cfg, obs=replace(model_cfg.obs, image_size=32))
    cfg = TrainConfig(data=store.path, batch_size=4)
    torch.manual_seed(0)
    model, ema, optimizer = build_training(cfg, method.model_cls(model_cfg, store.stats), torch.device("cpu"))
    assert optimizer.defaults["fused"]  # as on a GPU: one operator for all tensors
    model.train()
    batch = to_torch(
        PromptBatchDataset(store, model.data_spec(), frames=BENCHMARK.frames, batch_size=4, seed=2)[0],
        "cpu",
    )
    generator = torch.Generator().manual_seed(0)
    parts, totals = {}, Counter()

    def run(part: str, fn):
        with OpCounter() as counter:
            out = fn()
        parts[part] = sum(counter.counts.values())
        totals.update(counter.counts)
        return out

    for step in range(2):  # the first step also creates AdamW's state: count the second
        if step == 1:
            parts.clear()
            totals.clear()
        noise = model.draw_noise(batch, generator)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            loss = run("forward", lambda: model(batch, noise=noise))  # noqa: B023 - called at once
        optimizer.zero_grad(set_to_none=True)
        run("backward", loss.backward)
        run("clip+adamw", lambda: (torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0), optimizer.step()))
        run("ema", lambda: _ema_update(ema, model, 0.999))
    print(f"\n== {name} ({method_name}, {sum(p.numel() for p in model.parameters()) / 1e6:.1f}M parameters)")
    print("  ".join(f"{k} {v}" for k, v in parts.items()), f" whole step {sum(parts.values())}")
    for op, n in totals.most_common(top):
        print(f"  {n:6d}  {op}")
    return parts


def first_samples(batch: dict, n: int) -> dict:
    """`batch` cut to its first `n` window samples; the task contexts (their prompts) stay whole."""
    size = len(batch["context_index"])

    def cut(value):
        if isinstance(value, dict):
            return {k: cut(v) for k, v in value.items()}
        return value[:n] if value.shape[:1] == (size,) else value

    return {k: (v if k in ("context", "task") else cut(v)) for k, v in batch.items()}


def flop_budget(name: str, store: EpisodeStore, method_name: str) -> dict:
    """GFLOPs of the training step per window sample and per task (its prompt), at the preset's real image size."""
    if method_name == "icrt":
        print(f"\n== {name} (icrt): no FLOPs per window sample: ICRT's samples are whole demonstrations")
        return {}
    size, obs = PRESETS[name]
    method = get_method(method_name)
    model_cfg = method.config(size, obs, BENCHMARK)
    torch.manual_seed(0)
    model = method.model_cls(model_cfg, store.stats)
    model.train()
    batch = to_torch(
        PromptBatchDataset(store, model.data_spec(), frames=BENCHMARK.frames, batch_size=8, seed=2)[0],
        "cpu",
    )
    whole, half = step_flops(model, batch, amp=False), step_flops(model, first_samples(batch, 4), amp=False)
    sample = (whole - half) / 4
    context = batch["context"]
    out = {
        "GFLOP_per_sample": round(sample / 1e9, 3),
        "GFLOP_per_task": round((half - 4 * sample) / 1e9, 3),
    }
    line = (
        f"\n== {name} ({method_name}): {out['GFLOP_per_sample']} GFLOP per window sample (forward + backward), "
        f"{out['GFLOP_per_task']} per task"
    )
    if "valid" in context:  # a prompt demonstration (BPP); Goal-Image's context is one goal frame
        out["prompt_steps"] = int(context["valid"].sum())
        out["prompt_frames"] = int(context["obs"]["image"].shape[1]) if "image" in context["obs"] else 0
        line += f" for its {out['prompt_steps']}-step prompt ({out['prompt_frames']} frames)"
    if hasattr(model, "obs_encoder"):  # the sample's own observations through the encoder, forward and backward
        counter = FlopCounterMode(display=False)
        with counter:
            sum(f.float().sum() for f in model.obs_encoder(batch["obs"])).backward()
        model.zero_grad(set_to_none=True)
        out["obs_encoder_share"] = round(counter.get_total_flops() / 8 / sample, 3)
        line += f"; the observation encoder is {out['obs_encoder_share']:.1%} of a sample's"
    if name in TARGETS:
        out["target_TFLOP_per_s"] = round(TARGETS[name] * sample / 1e12, 2)
        line += f"; the issue's {TARGETS[name]:,} samples/s is {out['target_TFLOP_per_s']} TFLOP/s"
    print(line)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["paper", "cpu-image"], choices=list(PRESETS))
    parser.add_argument("--method", default="bpp")
    parser.add_argument("--amp", action="store_true", help="under CPU bf16 autocast (the casts a GPU step makes)")
    parser.add_argument("--top", type=int, default=15, help="most frequent operators listed")
    parser.add_argument("--measure", nargs="+", default=["ops", "flops"], choices=["ops", "flops"])
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-gpu"))
    args = parser.parse_args()
    path = args.data_dir / "profile-6.zarr"
    if not (path / "zarr.json").exists():
        draw_data.generate(replace(draw_data.PRESETS["cpu"], num_tasks=6, demos_per_task=5), path, progress=False)
    store = EpisodeStore(path)
    for name in args.presets:
        if "ops" in args.measure:
            count(name, store, args.method, args.amp, args.top)
        if "flops" in args.measure:
            flop_budget(name, store, args.method)


if __name__ == "__main__":
    main()
