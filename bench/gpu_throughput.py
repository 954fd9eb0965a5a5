"""What bounds `bpp train` and `act` on this machine, per preset: the loader, the model, or neither.

    python bench/gpu_throughput.py                        # on a GPU: the paper preset and cpu-image, < 8 minutes
    python bench/gpu_throughput.py --small                # the same measurements at toy sizes (a CPU, 1-2 minutes)

For each preset (a method's size preset observing a DrawAnything camera preset; ``paper`` is BPP's paper-sized
model on 224x224 frames, ``cpu-image`` the CPU-sized one on 64x64 frames), on a procedural training store generated
first, it measures:

* loader: samples/s of ONE loader process (what a `bpp train` worker does per batch: draw, render the frames it
  needs, collate), over batches after the first;
* pipeline: samples/s of `bpp train`'s whole loader with no model (its default worker processes, the batches
  passed to the training process, page-locked and copied to the device), with one worker and with the default
  number, and the megabytes a batch moves: what the loader can feed, where the loader line is one process's share;
* frames: the same with frame references (``bpp train --frames-on device``): one loader process building them,
  the device rendering a batch's frames from them alone (:class:`bpp.benchmarks.draw.device_render.DrawFrameTable`), and
  the whole pipeline, its default workers for that setting sending references and this process rendering them;
* model: samples/s of the training step of `bpp train` (`bpp.train.train_step`: forward, backward, clipping, AdamW,
  EMA) on a batch already on the device, at each batch size of ``--batch-sizes``, the peak memory, and the TFLOP/s
  it achieves (the step's FLOPs counted as ``bench/step_ops.py`` counts them: matrix products, convolutions and
  attention, on the same batch; set against the chip's peak, below); with
  variants (paper), the same with channels-first weights, with cuDNN's timed algorithm choice, with the 5x5-stem
  encoder of the CPU presets, and with fp32 GroupNorm under autocast, for comparison;
* end to end: samples/s of `bpp train` itself (a subprocess, its default loader workers), the median of its logged
  rates after the first interval; and at the largest end-to-end batch, again with ``--frames-on device``;
* compiled: the model-bound and end-to-end numbers again with `bpp train --compile MODE` (``--compile-modes``; on a
  GPU cudagraphs, the captured operators replayed as CUDA graphs, and reduce-overhead, inductor's kernels replayed
  so), with the warm-up's time (compiling); end to end with ``--frames-on device``;
* act: ms per inference call of :class:`bpp.policies.agent.PolicyAgent` (its prompt encoded once at reset), eager
  and, on a GPU, replayed from a CUDA graph, with the largest difference between the two;
* peak: the chip's own bf16 and fp32 matrix-product rates (TFLOP/s), measured first in the same run: the anchor the
  model-bound TFLOP/s are set against.

Every number is written to ``--out`` (JSON) as soon as it is measured, so a run cut short keeps what it measured;
a measurement that fails is recorded with its error and the next one runs.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bpp.benchmarks.draw import dataset as draw_data
from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.core.contract import device_frames
from bpp.data.contexts import task_context
from bpp.data.frame_refs import render_batch
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.nn.norm import GroupNorm
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, batch_loader, build_training, compiled, cpu_plan, train_step, uses_amp
from bpp.train_config import COMPILE_MODES
from bpp.utils import to_torch, usable_cores
from common import matmul_peak, step_flops, train_subprocess

PRESETS = {"paper": ("paper", "paper"), "cpu-image": ("cpu", "image64")}
"""Preset name -> (method size preset, DrawAnything observation preset)."""
BATCHES = {"paper": ([64, 128, 256], [64, 256]), "cpu-image": ([128, 256, 512], [256])}
"""Preset name -> (model-bound batch sizes, end-to-end batch sizes) on a GPU."""
PARTS = ("peak", "loader", "pipeline", "frames", "model", "variants", "e2e", "act", "compile")
"""What the script can measure (the module docstring says what each is); all by default."""


class Results:
    """The run's numbers, rewritten to `path` after every measurement."""

    def __init__(self, path: Path, meta: dict):
        self.path, self.data = path, {"meta": meta, "presets": {}}
        path.parent.mkdir(parents=True, exist_ok=True)
        self.save()

    def record(self, preset: str, name: str, value) -> None:
        self.data["presets"].setdefault(preset, {})[name] = value
        self.save()
        print(f"[{preset}] {name}: {json.dumps(value)}", flush=True)

    def save(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1))
        tmp.replace(self.path)


def measure(results: Results, preset: str, name: str, fn) -> None:
    """Run one measurement; a failure is recorded (with its traceback printed) and does not stop the run."""
    try:
        results.record(preset, name, fn())
    except Exception as error:  # noqa: BLE001 - a benchmark reports every failure and goes on
        traceback.print_exc()
        results.record(preset, name, {"error": f"{type(error).__name__}: {error}"})


@contextlib.contextmanager
def fp32_group_norm():
    """Models built inside normalise in fp32 under autocast (torch's own GroupNorm), for comparison."""
    saved = GroupNorm.forward
    GroupNorm.forward = torch.nn.GroupNorm.forward
    try:
        yield
    finally:
        GroupNorm.forward = saved


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def loader_rate(store: EpisodeStore, spec, batch_size: int, batches: int, cache_bytes: int, refs=False) -> dict:
    """Samples/s of one loader process over `batches` batches after a first one (which loads the store's arrays);
    with `refs`, batches of frame references (``bpp train --frames-on device``), which render nothing."""
    data = PromptBatchDataset(
        store,
        spec,
        frames=BENCHMARK.frames,
        batch_size=batch_size,
        seed=1,
        frame_cache_bytes=cache_bytes,
        frame_refs=refs,
    )
    data[0]
    t0 = time.perf_counter()
    for i in range(1, batches + 1):
        data[i]
    seconds = time.perf_counter() - t0
    return {
        "samples_per_s": round(batches * batch_size / seconds, 1),
        "ms_per_batch": round(1000 * seconds / batches, 1),
        "whole_episodes": data.whole_episodes,
    }


def tensor_bytes(batch) -> int:
    if isinstance(batch, dict):
        return sum(tensor_bytes(v) for v in batch.values())
    return batch.nbytes if isinstance(batch, (np.ndarray, torch.Tensor)) else 0


def pipeline_rate(
    store: EpisodeStore, spec, batch_size: int, device: torch.device, workers: int, batches: int, renderer=None
) -> dict:
    """Samples/s of `bpp train`'s whole loader with no model: `workers` loader processes (at least 1) sharing the
    frame cache as training's do, their batches passed to this process and, on a GPU, page-locked and copied to it.

    The rate is that of the second half of `batches` (at least 24 per worker). The first half holds the workers'
    start and the 4 batches each builds ahead. With no model the queue is empty by the second half, so that half
    runs at what the whole pipeline delivers: the workers' rate unless this process cannot take batches as fast.
    On a CPU this process does not read the batches (the copy to the device is none), so the numbers there leave out
    what a training process spends reading them.

    With a `renderer` (``bpp train --frames-on device``), the workers send frame references and this process renders
    them on the device, as training does: the rate then includes the rendering."""
    workers = max(1, workers)
    cache = TrainConfig(data=store.path).frame_cache_share(workers)
    batches = max(batches, 24 * workers)
    refs = renderer is not None
    data = PromptBatchDataset(
        store,
        spec,
        frames=BENCHMARK.frames,
        batch_size=batch_size,
        num_batches=batches,
        seed=1,
        frame_cache_bytes=cache,
        frame_refs=refs,
    )
    loader = batch_loader(data, range(batches), workers, pin_memory=device.type == "cuda")
    t0 = time.perf_counter()
    half, timed_bytes = None, 0
    for i, batch in enumerate(loader):
        if half is not None:
            timed_bytes += tensor_bytes(batch)
        if renderer is not None:
            batch = render_batch(batch, spec, renderer)
        to_torch(batch, device)
        if i + 1 == batches // 2:
            synchronize(device)
            half = time.perf_counter()
    synchronize(device)
    end = time.perf_counter()
    timed = batches - batches // 2
    return {
        "workers": workers,
        "samples_per_s": round(timed * batch_size / (end - half), 1),
        "first_half_s": round(half - t0, 2),
        "MB_per_batch": round(timed_bytes / timed / 2**20, 2),
        "MB_per_s": round(timed_bytes / 2**20 / (end - half), 1),
    }


def device_render_rate(store: EpisodeStore, spec, batch_size: int, device: torch.device, batches: int, renderer):
    """Samples/s of `renderer` (:class:`bpp.benchmarks.draw.device_render.DrawFrameTable`) rendering batches' frames on
    `device` from references (``bpp train --frames-on device``), the batches built beforehand; after a first batch."""
    data = PromptBatchDataset(store, spec, frames=BENCHMARK.frames, batch_size=batch_size, seed=1, frame_refs=True)
    ready = [data[i] for i in range(batches + 1)]
    first = ready[0]
    frames = sum(first["obs"][k][..., 0].size for k in spec.image_keys)
    if "obs" in first["context"]:
        frames += sum(first["context"]["obs"][k][..., 0].size for k in spec.image_keys)
    render_batch(ready[0], spec, renderer)
    synchronize(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    for batch in ready[1:]:
        render_batch(batch, spec, renderer)
    synchronize(device)
    seconds = time.perf_counter() - t0
    out = {
        "samples_per_s": round(batches * batch_size / seconds, 1),
        "ms_per_batch": round(1000 * seconds / batches, 2),
        "frames_per_batch": int(frames),
    }
    if device.type == "cuda":
        out["peak_memory_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
    return out


def op_times(step, steps: int, device: torch.device, top: int = 12) -> dict:
    """Where `steps` calls of `step` (given 0, 1, ...) spend the device's time (on a CPU: its own), per operator,
    ms per step: the `top` operators by their own (self) time, and the total. On a GPU this says which kernels the
    step waits on: convolutions, norms, layout copies, pointwise operations."""
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        for i in range(steps):
            step(i)
        synchronize(device)
    key = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    events = [(e.key, getattr(e, key) / 1000 / steps) for e in prof.key_averages()]  # us -> ms per step
    events.sort(key=lambda kv: -kv[1])
    return {
        "total_ms": round(sum(ms for _, ms in events), 2),
        "top_ms": {name: round(ms, 2) for name, ms in events[:top]},
    }


def model_rate(
    store,
    method,
    model_cfg,
    device,
    batch_size: int,
    steps: int,
    channels_last: bool = True,
    timed_convs=False,
    compile: str = "off",
    profile_steps: int = 0,
) -> dict:
    """Samples/s of bpp.train's training step on one batch already on `device`, and the peak memory;
    `timed_convs`: let cuDNN time its convolution algorithms (fixed shapes here; `bpp train` does not); `compile`:
    `bpp train --compile`'s mode (the warm-up steps, timed apart, then compile and record); `profile_steps`: that
    many more steps under torch's profiler, for the time per operator (:func:`op_times`)."""
    torch.backends.cudnn.benchmark = timed_convs
    cfg = TrainConfig(
        data=store.path, method=method.name, batch_size=batch_size, channels_last=channels_last, compile=compile
    )
    torch.manual_seed(0)
    torch._dynamo.reset()
    model, ema, optimizer = build_training(cfg, method.model_cls(model_cfg, store.stats), device)
    model.train()
    spec = model.data_spec()
    data = PromptBatchDataset(
        store,
        spec,
        frames=BENCHMARK.frames,
        batch_size=batch_size,
        seed=2,
        pad_to_multiple=cfg.padding(spec),
    )
    batch = to_torch(data[0], device)
    amp = uses_amp(cfg, device)
    net = compiled(cfg, model)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    warmup = 3
    t_start = time.perf_counter()
    for step in range(warmup + steps):
        if step == warmup:
            synchronize(device)
            t0 = time.perf_counter()
        loss, _ = train_step(cfg, net, model, ema, optimizer, batch, step, amp)
    loss = float(loss.detach())  # waits for the device
    seconds = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else 0  # before the counted step below
    flops = step_flops(model, batch, amp)  # the same math as the compiled step's, counted on the eager model
    out = {
        "batch_size": batch_size,
        "samples_per_s": round(steps * batch_size / seconds, 1),
        "ms_per_step": round(1000 * seconds / steps, 1),
        "GFLOP_per_step": round(flops / 1e9, 1),
        "TFLOP_per_s": round(flops * steps / seconds / 1e12, 3),
        "warmup_s": round(t0 - t_start, 1),
        "loss": round(loss, 4),
        "parameters_M": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
    }
    if device.type == "cuda":
        out["peak_memory_GiB"] = round(peak / 2**30, 2)
    if profile_steps:
        step = functools.partial(train_step, cfg, net, model, ema, optimizer, batch)
        out["time_per_operator"] = op_times(lambda i: step(warmup + steps + i, amp), profile_steps, device)
    del model, ema, optimizer, batch
    torch.backends.cudnn.benchmark = False
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return out


def end_to_end_rate(store_path: Path, size: str, obs: str, batch_size: int, steps: int, log_every: int, extra=()):
    """Samples/s of `bpp train` (a subprocess with its default loader workers): the median logged rate after the
    first interval, read back from its TensorBoard log."""
    arguments = ["--data", str(store_path), "--preset", size, "--obs", obs, "--steps", str(steps)]
    arguments += ["--batch-size", str(batch_size), "--log-every", str(log_every), "--save-every", str(10 * steps)]
    wall, logged, stdout = train_subprocess([*arguments, "--warmup-steps", "10", *extra], ("train/samples_per_s",))
    rates = [value for _, value in logged["train/samples_per_s"]]
    workers = [line for line in stdout.splitlines() if "loader workers" in line]
    return {
        "batch_size": batch_size,
        "samples_per_s": round(float(np.median(rates[1:] if len(rates) > 1 else rates)), 1),
        "logged_rates": [round(r, 1) for r in rates],
        "wall_s": round(wall, 1),
        "setup": workers[0].strip() if workers else "",
    }


def act_latency(store, method, model_cfg, device, calls: int) -> dict:
    """ms per inference call (one chunk of actions), eager and from a CUDA graph (GPU), untrained weights."""
    torch.manual_seed(0)
    model = method.model_cls(model_cfg, store.stats)
    agent = PolicyAgent(model, device)
    spec = agent.data_spec
    agent.reset(task_context(store, 0, spec, BENCHMARK.frames), seed=0)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (spec.image_size, spec.image_size, 3), dtype=np.uint8)
    obs = {k: store.array(k)[0] for k in spec.lowdim_keys} | {k: frame for k in spec.image_keys}
    agent.act(obs)

    def timed(graphs: bool) -> tuple[float, np.ndarray]:
        model.head.cuda_graphs = graphs
        agent.generators = [torch.Generator(device).manual_seed(0)]
        first = agent.predict_chunk()  # and warm-up (the graph is recorded here)
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            agent.predict_chunk()
            times.append(time.perf_counter() - t0)
        return 1000 * float(np.median(times)), first

    out = {"prompt_steps": int(store.episode_slice(0).stop - store.episode_slice(0).start)}
    eager_ms, eager = timed(False)
    out["eager_ms"] = round(eager_ms, 2)
    if device.type == "cuda":
        graph_ms, graphed = timed(True)
        out["cuda_graph_ms"] = round(graph_ms, 2)
        out["cuda_graph_max_abs_diff"] = float(np.abs(graphed - eager).max())
    return out


def bench_preset(results: Results, name: str, store: EpisodeStore, device: torch.device, args) -> None:
    """Every measurement of one preset (see the module docstring)."""
    method, small = get_method("bpp"), args.small
    size, obs = PRESETS[name]
    size = "debug" if small else size
    model_cfg = method.config(size, obs, BENCHMARK)
    if small:  # toy frames too: the script's logic, not its numbers
        model_cfg = replace(model_cfg, obs=replace(model_cfg.obs, image_size=32))
    spec = method.model_cls(model_cfg, store.stats).data_spec()
    batch_sizes, e2e_sizes = ([8], [8]) if small else BATCHES[name]
    batch_sizes = args.batch_sizes or batch_sizes
    steps = 3 if small else 15
    # A loader process's share of the frame cache when `bpp train` runs its default workers on this machine.
    cache = 0 if small else TrainConfig(data=store.path).frame_cache_share(usable_cores() - 2)
    parts = set(args.parts)
    if "loader" in parts:
        measure(results, name, "loader", lambda: loader_rate(store, spec, batch_sizes[0], 3 if small else 20, cache))
    if "pipeline" in parts:  # `bpp train`'s default workers; on a CPU (where it has none) one per core
        default = cpu_plan(TrainConfig(data=store.path), device)[0] or usable_cores()
        for workers in sorted({1, default}):
            measure(
                results,
                name,
                f"pipeline_w{workers}",
                lambda w=workers: pipeline_rate(store, spec, e2e_sizes[0], device, w, 8 if small else 40),
            )
    if "frames" in parts:  # frames rendered on the device from references (`bpp train --frames-on device`)
        b = e2e_sizes[-1]
        measure(results, name, "loader_refs", lambda: loader_rate(store, spec, b, 3 if small else 20, 0, refs=True))
        t0 = time.perf_counter()
        renderer = device_frames(BENCHMARK, store, device)
        results.record(name, "device_frames_table_s", round(time.perf_counter() - t0, 2))
        render = functools.partial(device_render_rate, store, spec, b, device, 3 if small else 20, renderer)
        measure(results, name, f"device_render_b{b}", render)
        on_device = replace(TrainConfig(data=store.path), frames_on="device")
        workers = cpu_plan(on_device, device)[0] or usable_cores()
        measure(
            results,
            name,
            f"pipeline_frames_on_device_w{workers}",
            lambda: pipeline_rate(store, spec, b, device, workers, 8 if small else 40, renderer),
        )
    for b in batch_sizes if "model" in parts else ():
        measure(results, name, f"model_b{b}", lambda b=b: model_rate(store, method, model_cfg, device, b, steps))
    if "variants" in parts and (small or name == "paper"):
        b = batch_sizes[0]
        first = f"model_b{b}_channels_first"
        measure(results, name, first, lambda: model_rate(store, method, model_cfg, device, b, steps, False))
        timed = f"model_b{b}_cudnn_benchmark"
        measure(results, name, timed, lambda: model_rate(store, method, model_cfg, device, b, steps, timed_convs=True))
        conv5 = replace(model_cfg, obs=replace(model_cfg.obs, image_stem="conv5"))
        measure(results, name, f"model_b{b}_conv5_stem", lambda: model_rate(store, method, conv5, device, b, steps))
        with fp32_group_norm():
            fp32 = f"model_b{b}_fp32_groupnorm"
            measure(results, name, fp32, lambda: model_rate(store, method, model_cfg, device, b, steps))
    extra = ["--model.obs.image-size", "32"] if small else []
    e2e_steps, log_every = (6, 2) if small else (150, 25)
    for b in e2e_sizes if "e2e" in parts else ():
        measure(
            results,
            name,
            f"end_to_end_b{b}",
            lambda b=b: end_to_end_rate(Path(store.path), size, obs, b, e2e_steps, log_every, extra),
        )
    on_device = [*extra, "--frames-on", "device"]
    for b in e2e_sizes[-1:] if "e2e" in parts else ():  # the same, frames rendered on the device
        measure(
            results,
            name,
            f"end_to_end_b{b}_frames_on_device",
            lambda b=b: end_to_end_rate(Path(store.path), size, obs, b, e2e_steps, log_every, on_device),
        )
    if "compile" in parts and "model" not in parts:  # the eager step next to the compiled ones, in this same run
        b = batch_sizes[-1]  # with the time per operator of 3 more steps
        profiled = functools.partial(model_rate, store, method, model_cfg, device, b, steps, profile_steps=3)
        measure(results, name, f"model_b{b}", profiled)
    for mode in args.compile_modes if "compile" in parts else ():
        for b in batch_sizes[-1:]:  # at the largest batch size only: each compiles anew
            measure(
                results,
                name,
                f"model_b{b}_compile_{mode}",
                lambda b=b, mode=mode: model_rate(store, method, model_cfg, device, b, steps, compile=mode),
            )
        for b in e2e_sizes[-1:]:
            compiled_extra = [*on_device, "--compile", mode]  # against the eager run with frames on the device
            measure(
                results,
                name,
                f"end_to_end_b{b}_compile_{mode}",
                lambda b=b, e=compiled_extra: end_to_end_rate(Path(store.path), size, obs, b, e2e_steps, log_every, e),
            )
    if "act" in parts:
        measure(results, name, "act", lambda: act_latency(store, method, model_cfg, device, 5 if small else 30))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--small", action="store_true", help="toy sizes: check the script on a CPU")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=None, help="model-bound batch sizes")
    parser.add_argument(
        "--parts",
        nargs="+",
        default=list(PARTS),
        choices=PARTS,
        help="what to measure (variants, paper only: channels-first, timed cuDNN, the 5x5 stem, fp32 GroupNorm; "
        "compile: model-bound and end to end with `bpp train --compile` in each of --compile-modes)",
    )
    parser.add_argument(
        "--compile-modes",
        nargs="+",
        default=None,
        choices=[m for m in COMPILE_MODES if m != "off"],
        help="`bpp train --compile` modes to measure (default: cudagraphs and reduce-overhead on a GPU, default on a "
        "CPU)",
    )
    parser.add_argument("--tasks", type=int, default=None, help="procedural tasks in the training store")
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-gpu"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/gpu_throughput.json"))
    args = parser.parse_args()

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    args.compile_modes = args.compile_modes or (
        ["cudagraphs", "reduce-overhead"] if device.type == "cuda" else ["default"]
    )
    small = args.small
    results = Results(
        args.out,
        {
            "command": " ".join(sys.argv),
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
            "cores": usable_cores(),
            "torch": torch.__version__,
            "small": small,
            "date": time.strftime("%Y-%m-%d %H:%M"),
        },
    )
    tasks = args.tasks or (6 if small else 200)
    store_path = args.data_dir / f"procedural-{tasks}.zarr"
    if not (store_path / "zarr.json").exists():
        cfg = replace(draw_data.PRESETS["cpu"], num_tasks=tasks, demos_per_task=3 if small else 5)
        t0 = time.perf_counter()
        draw_data.generate(cfg, store_path, overwrite=True, progress=False)
        print(f"generated {store_path} in {time.perf_counter() - t0:.1f} s", flush=True)
    store = EpisodeStore(store_path)
    if "peak" in args.parts:
        sizes = (256,) if small else (4096, 8192)
        for dtype in (torch.bfloat16, torch.float32):
            rate = lambda dtype=dtype: round(matmul_peak(dtype, usable_cores(), sizes, 1.0, device) / 1e3, 3)  # noqa: E731
            measure(results, "chip", f"matmul_tflops_{str(dtype).removeprefix('torch.')}", rate)
    for name in args.presets:
        bench_preset(results, name, store, device, args)
    print(json.dumps(results.data, indent=1))


if __name__ == "__main__":
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    main()
