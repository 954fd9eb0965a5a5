"""Does reduced precision pay on this CPU? The main job's training step in fp32 and under bf16 autocast, side by side.

    python bench/cpu_precision.py                      # BPP, cpu size, board observations, batch 64, 8 tasks
    python bench/cpu_precision.py --obs board-image --rounds 5
    python bench/cpu_precision.py --limit              # what bounds the step: its convolutions, profiled
    python bench/cpu_precision.py --profile --batch-size 256   # where each precision's step spends its time

In one process on `--threads` torch threads (default 1): the cores' matrix-product rate in fp32 and bf16 (the
yardstick), a 1D convolution at the action decoder's largest size with its backward in both precisions, then the
whole training step (``bpp.train.train_step``: loss, backward, clipping, fused AdamW, EMA) on the same batches in
fp32 and under bf16 autocast with fp32 weights, alternated for `--rounds` rounds. Prints each round and the medians.

With --limit: the matrix-product rate in fp32, bf16 and fp16, every 1D convolution of the action decoder at its
real sizes (forward and both gradients) in fp32, and the same convolution written as one matrix product of its
unfolded input in bf16 (what reduced precision could give a convolution where bf16 products are fast, as with AMX),
and a profile of 10 training steps in fp32, then under bf16 autocast: the share of a step spent in convolutions, and
so the speed-up over the fp32 step that each could reach if everything else took no time at all; then the same
bound with the parameter update's memory traffic added at the copy bandwidth measured in the same call (fp32 weights,
AdamW's moments and the EMA cannot be updated faster than they can be streamed).

With --profile: the operators that take most of `--steps` profiled steps in either precision, each with its time in
both (what reduced precision speeds up on this CPU, and what it slows down).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from einops import rearrange
from torch.profiler import ProfilerActivity, profile

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import PRESETS as DATA_PRESETS
from bpp.benchmarks.draw.dataset import generate
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore, stored_with
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, build_training, train_step
from bpp.utils import to_torch
from common import copy_bandwidth, matmul_peak

# A step reads and writes every parameter's fp32 weight, AdamW's two moments and the EMA's copy at least once (the
# gradient's read counted as free): the update's memory traffic, bytes per parameter.
UPDATE_BYTES_PER_PARAMETER = 32


def conv_rate(dtype: torch.dtype, seconds: float = 1.0) -> float:
    """GFLOP/s of a 256 -> 256 channel, kernel-5 convolution over 4 steps at batch 64 (the decoder's innermost
    level, its largest product), forward and both gradients."""
    x = torch.randn(64, 256, 4, dtype=dtype, requires_grad=True)
    w = torch.randn(256, 256, 5, dtype=dtype, requires_grad=True)
    return gradient_rate(lambda x, w: F.conv1d(x, w, padding=2), x, w, 3 * 2 * 64 * 4 * 256 * 256 * 5, seconds)


def gradient_rate(conv, x: torch.Tensor, w: torch.Tensor, flops: float, seconds: float = 0.5) -> float:
    """GFLOP/s of ``conv(x, w)`` with both gradients."""
    conv(x, w).sum().backward()
    count, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        conv(x, w).sum().backward()
        count += 1
    return flops * count / elapsed / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="bpp")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--obs", default="board")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--tasks-per-batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=20, help="timed steps per precision and round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--tasks", type=int, default=500, help="procedural tasks in the store (the demo's 500)")
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-speed-history"))
    parser.add_argument("--limit", action="store_true", help="profile what bounds an fp32 step instead")
    parser.add_argument("--profile", action="store_true", help="profile the step's operators in both precisions")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    data_cfg = replace(DATA_PRESETS["cpu"], num_tasks=args.tasks)
    path = args.data_dir / f"train-{args.tasks}.zarr"
    if stored_with(path, data_cfg) is None:
        generate(data_cfg, path, overwrite=True)
    store = EpisodeStore(path)
    model_cfg = get_method(args.method).config(args.preset, args.obs, BENCHMARK)
    cfg = TrainConfig(data=path, method=args.method, batch_size=args.batch_size, tasks_per_batch=args.tasks_per_batch)
    cpu = torch.device("cpu")
    torch.manual_seed(0)
    model, ema, optimizer = build_training(cfg, get_method(args.method).model_cls(model_cfg, store.stats), cpu)
    dataset = PromptBatchDataset(
        store, model.data_spec(), frames=BENCHMARK.frames, batch_size=args.batch_size, num_batches=args.steps + 3,
        tasks_per_batch=args.tasks_per_batch, frame_cache_bytes=2**31,
    )  # fmt: skip
    batches = [to_torch(dataset[i], cpu) for i in range(args.steps + 3)]

    if args.limit:
        limit(cfg, model, ema, optimizer, batches, args.threads)
        return
    if args.profile:
        profile_precisions(cfg, model, ema, optimizer, batches, args.steps)
        return
    print(
        f"matmul GFLOP/s on {args.threads} thread(s): fp32 {matmul_peak(torch.float32, args.threads):.1f}, "
        f"bf16 {matmul_peak(torch.bfloat16, args.threads):.1f}; decoder convolution with its gradients: "
        f"fp32 {conv_rate(torch.float32):.1f}, bf16 {conv_rate(torch.bfloat16):.1f}"
    )
    rates: dict[str, list[float]] = {"fp32": [], "bf16 autocast": []}
    for round_ in range(args.rounds):
        for name, amp in (("fp32", False), ("bf16 autocast", True)):
            for step in range(3):  # warm-up: the allocator, oneDNN's kernel choices
                train_step(cfg, model, model, ema, optimizer, batches[step], step, amp)
            t0 = time.perf_counter()
            for step in range(3, args.steps + 3):
                loss, _ = train_step(cfg, model, model, ema, optimizer, batches[step], step, amp)
            float(loss.detach())
            rate = args.steps * args.batch_size / (time.perf_counter() - t0)
            rates[name].append(rate)
            print(f"round {round_}: {name:>13}: {rate:6.1f} samples/s")
    fp32 = float(np.median(rates["fp32"]))
    for name, values in rates.items():
        print(f"{name:>13}: median {np.median(values):6.1f} samples/s, {np.median(values) / fp32:.3f}x fp32")


def profile_precisions(cfg, model, ema, optimizer, batches, steps: int, top: int = 8) -> None:
    """Print the operators that take most of `steps` profiled training steps in fp32 or under bf16 autocast, with
    their self CPU time (ms, all steps together) in both."""
    times = {}
    for name, amp in (("fp32", False), ("bf16", True)):
        for step in range(3):
            train_step(cfg, model, model, ema, optimizer, batches[step], step, amp)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for step in range(3, steps + 3):
                train_step(cfg, model, model, ema, optimizer, batches[step], step, amp)
        times[name] = {e.key: e.self_cpu_time_total / 1e3 for e in prof.key_averages()}
    print(f"self CPU time of {steps} steps (ms): total fp32 {sum(times['fp32'].values()):.0f}, "
          f"bf16 {sum(times['bf16'].values()):.0f}")  # fmt: skip
    keys = sorted(set(times["fp32"]) | set(times["bf16"]), key=lambda k: -max(t.get(k, 0.0) for t in times.values()))
    for key in keys[:top]:
        print(f"{key[:64]:64s} fp32 {times['fp32'].get(key, 0.0):8.1f}  bf16 {times['bf16'].get(key, 0.0):8.1f}")


def decoder_convolutions(model) -> tuple[list, list[tuple[int, int, int, int]]]:
    """Hooks that record (in channels, out channels, kernel, steps) of every 1D convolution a forward pass runs, and
    the list they fill."""
    sizes = []

    def record(module, inputs, _output):
        sizes.append((module.in_channels, module.out_channels, module.kernel_size[0], inputs[0].shape[-1]))

    hooks = [m.register_forward_hook(record) for m in model.modules() if isinstance(m, torch.nn.Conv1d)]
    return hooks, sizes


def unfolded_conv1d(x: torch.Tensor, w: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``F.conv1d(x, w, padding=k // 2)`` as one matrix product of the unfolded input, computed in `dtype`."""
    k = w.shape[-1]
    columns = rearrange(F.pad(x, (k // 2, k // 2)).unfold(2, k, 1), "b c t k -> (b t) (c k)")
    y = (columns.to(dtype) @ rearrange(w, "o c k -> (c k) o").to(dtype)).float()
    return rearrange(y, "(b t) o -> b o t", b=x.shape[0])


def limit(cfg, model, ema, optimizer, batches, threads: int) -> None:
    """Print what bounds a step on this CPU, in fp32 and under bf16 autocast (see the module's docstring)."""
    rates = {dt: matmul_peak(dt, threads) for dt in (torch.float32, torch.bfloat16, torch.float16)}
    print("matmul GFLOP/s: " + ", ".join(f"{str(dt).split('.')[-1]} {r:.1f}" for dt, r in rates.items()))
    hooks, sizes = decoder_convolutions(model)
    train_step(cfg, model, model, ema, optimizer, batches[0], 0, False)
    for h in hooks:
        h.remove()
    batch = cfg.batch_size
    for c_in, c_out, k, t in sorted(set(sizes)):
        x = torch.randn(batch, c_in, t, requires_grad=True)
        w = torch.randn(c_out, c_in, k, requires_grad=True)
        flops = 3 * 2 * batch * t * c_in * c_out * k
        rate = gradient_rate(lambda x, w, pad=k // 2: F.conv1d(x, w, padding=pad), x, w, flops)
        unfolded = gradient_rate(lambda x, w: unfolded_conv1d(x, w, torch.bfloat16), x, w, flops)
        print(f"conv1d {c_in:4d} -> {c_out:4d}, kernel {k}, {t:2d} steps: {rate:6.1f} GFLOP/s fp32 "
              f"({rate / rates[torch.float32]:.0%} of the fp32 matmul rate); as a bf16 product {unfolded:6.1f} "
              f"({unfolded / rate:.2f}x)")  # fmt: skip
    fp32_ms, fp32_share = step_and_convolutions(cfg, model, ema, optimizer, batches, False)
    print(f"a step: {fp32_ms:.1f} ms unprofiled; convolutions {fp32_share:.1%} of its profiled time: with everything "
          f"else taking no time the step would run {1 / fp32_share:.2f}x faster at these kernels' speed")  # fmt: skip
    bf16_ms, bf16_share = step_and_convolutions(cfg, model, ema, optimizer, batches, True)
    bound = fp32_ms / (bf16_share * bf16_ms)
    print(f"under bf16 autocast: a step {bf16_ms:.1f} ms ({fp32_ms / bf16_ms:.3f}x), convolutions {bf16_share:.1%}: "
          f"with everything else taking no time, at most {bound:.2f}x the fp32 step")  # fmt: skip
    parameters = sum(p.numel() for p in model.parameters())
    bandwidth = copy_bandwidth(threads)
    update_ms = UPDATE_BYTES_PER_PARAMETER * parameters / (bandwidth * 1e9) * 1e3
    print(f"the parameter update's memory traffic ({parameters / 1e6:.2f} M parameters x {UPDATE_BYTES_PER_PARAMETER} "
          f"bytes at {bandwidth:.1f} GB/s, this core's copy rate) takes at least {update_ms:.1f} ms: with it and the "
          f"convolutions, everything else free, at most {fp32_ms / (fp32_share * fp32_ms + update_ms):.2f}x in fp32 "
          f"and {fp32_ms / (bf16_share * bf16_ms + update_ms):.2f}x under bf16")  # fmt: skip


def step_and_convolutions(cfg, model, ema, optimizer, batches, amp: bool, steps: int = 10) -> tuple[float, float]:
    """A training step's unprofiled time (ms, the mean of `steps`) in fp32 or under bf16 autocast, and the share of
    its profiled time spent in convolutions (forward and backward)."""
    for step in range(1, 4):
        train_step(cfg, model, model, ema, optimizer, batches[step], step, amp)
    t0 = time.perf_counter()
    for step in range(4, 4 + steps):
        train_step(cfg, model, model, ema, optimizer, batches[step % len(batches)], step, amp)
    step_ms = (time.perf_counter() - t0) / steps * 1e3
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for step in range(4, 4 + steps):
            train_step(cfg, model, model, ema, optimizer, batches[step % len(batches)], step, amp)
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    return step_ms, sum(e.self_cpu_time_total for e in events if "convolution" in e.key) / total


if __name__ == "__main__":
    main()
