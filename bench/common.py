"""Helpers that several scripts in bench/ share: DrawAnything and LIBERO-Gen training runs that are reused, finished
or resumed; training budgets per method; `bpp train` as a subprocess and its logged rates; a training step's FLOPs;
the machine's yardsticks (matrix-product rate, copy bandwidth); paired differences between evaluations.

The scripts import it as a sibling module (``from common import train_run``): ``python bench/<script>.py`` puts
bench/ first on the module path, so nothing needs to change ``sys.path``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.checkpoint import Checkpoint, read_state, resolve_checkpoint
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.data.store import EpisodeStore
from bpp.evaluation.evaluate import resolve_tasks
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
from bpp.utils import to_dict, to_torch, write_json_atomic

NAMES = {"bpp": "BPP", "goal_image": "Goal-Image", "icrt": "ICRT", "language": "Language"}
"""Each method's name in reports and figures."""


def train_run(
    method: str,
    preset: str,
    obs: str,
    store: EpisodeStore,
    run: Path,
    steps: int,
    seed: int,
    batch_size: int = 64,
    tasks_per_batch: int = 1,
    threads: int = 0,
    model_cfg=None,
    loader_workers: int = 0,
    compile: str = "off",
    frames_on: str = "loader",
) -> float:
    """Train (or finish, or reuse) one run of size preset `preset` observing DrawAnything's observation preset
    `obs` (or of `model_cfg`, a variation of it); returns its training wall time in seconds (summed over
    interrupted and resumed runs)."""
    model_cfg = model_cfg or get_method(method).config(preset, obs, BENCHMARK)
    recorded = run / "config.json"
    if recorded.is_file():
        stored = json.loads(recorded.read_text()).get("model_config")
        if stored != to_dict(model_cfg):
            raise SystemExit(
                f"{run} was trained with another {method} configuration than today's `{preset}` preset observing "
                f"`{obs}` (a preset changed since); delete it or pass another --runs folder"
            )
    timing = run / "train_seconds.json"
    spent = json.loads(timing.read_text())["seconds"] if timing.is_file() else 0.0
    if trained_to(run, steps):
        return spent
    resume = (run / "checkpoints" / "last").is_file()
    t0 = time.perf_counter()
    cfg = TrainConfig(
        data=store.path,
        out=run,
        method=method,
        steps=steps,
        batch_size=batch_size,
        tasks_per_batch=tasks_per_batch,
        seed=seed,
        threads=threads,
        workers=loader_workers,
        compile=compile,
        frames_on=frames_on,
        resume=resume,
        save_every=500,
    )
    try:
        train(cfg, model_cfg)
    finally:  # an interrupted run (Ctrl-C) keeps its time too, including steps it will redo from the last checkpoint
        spent += time.perf_counter() - t0
        write_json_atomic(timing, {"seconds": spent})
    return spent


def trained_to(run: Path, steps: int) -> bool:
    """Whether `run` holds a checkpoint of at least `steps` training steps."""
    with contextlib.suppress(OSError, ValueError):
        return read_state(resolve_checkpoint(run))["step"] >= steps
    return False


def _per_method(items: list[str]) -> dict[str, int]:
    """["bpp=6000", "icrt=4000"] -> {"bpp": 6000, "icrt": 4000}."""
    return {k: int(v) for k, v in (item.split("=", 1) for item in items)}


def add_budget_arguments(parser: argparse.ArgumentParser) -> None:
    """--steps, --default-steps and --batch: each method's training steps and batch size (see :func:`budgets`)."""
    parser.add_argument("--steps", nargs="*", default=[], help="per-method training steps, e.g. bpp=6000 icrt=4000")
    parser.add_argument("--default-steps", type=int, default=6000)
    parser.add_argument(
        "--batch",
        nargs="*",
        default=["icrt=16"],
        help="per-method batch sizes (default 64 windows; ICRT's samples are whole demonstrations)",
    )


def budgets(args) -> tuple[dict[str, int], dict[str, int]]:
    """(steps, batch size) of each of ``args.methods`` from the flags :func:`add_budget_arguments` adds."""
    steps = {m: args.default_steps for m in args.methods} | _per_method(args.steps)
    return steps, {m: 64 for m in args.methods} | _per_method(args.batch)


def train_subprocess(
    arguments: list[str], scalars: tuple[str, ...], env: dict | None = None
) -> tuple[float, dict, str]:
    """Run `bpp train ARGUMENTS --out <temporary run>` as a subprocess (in environment `env`, default this one's):
    (wall seconds, {scalar tag: [(step, value)]} read back from its TensorBoard log, its standard output)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    with tempfile.TemporaryDirectory(prefix="bpp-train-") as run:
        command = [sys.executable, "-m", "bpp.cli", "train", *arguments, "--out", f"{run}/run"]
        t0 = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if done.returncode:
            raise RuntimeError(f"bpp train {' '.join(arguments)} failed ({done.returncode}): {done.stderr[-3000:]}")
        events = EventAccumulator(f"{run}/run/tb")
        events.Reload()
        return wall, {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in scalars}, done.stdout


def add_main_job_arguments(parser: argparse.ArgumentParser, steps: int) -> None:
    """The flags of a `bpp train` run in the main job's setting (:func:`train_rate` reads them)."""
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--obs", default="board")
    parser.add_argument("--steps", type=int, default=steps)
    parser.add_argument("--log-every", type=int, default=25)
    parser.add_argument("--tasks", type=int, default=500, help="procedural tasks in the store (the demo's 500)")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--tasks-per-batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)


def train_rate(store: Path, args, extra: list[str], env: dict | None = None) -> dict:
    """One `bpp train` on `store` with :func:`add_main_job_arguments`' flags and `extra` (in environment `env`): its
    wall time, first interval (which holds any compilation), median samples/s after two intervals, and losses."""
    arguments = ["--data", str(store), "--preset", args.preset, "--obs", args.obs, "--steps", str(args.steps)]
    arguments += ["--batch-size", str(args.batch_size), "--tasks-per-batch", str(args.tasks_per_batch)]
    arguments += ["--threads", str(args.threads), "--log-every", str(args.log_every)]
    arguments += ["--save-every", str(10 * args.steps), *extra]
    wall, logged, _ = train_subprocess(arguments, ("train/samples_per_s", "train/loss"), env=env)
    rates = [value for _, value in logged["train/samples_per_s"]]
    losses = dict(logged["train/loss"])
    steady = rates[2:] if len(rates) > 2 else rates[-1:]
    first = args.log_every * args.batch_size / rates[0]  # seconds of the first interval (rates are per interval)
    return {
        "wall_s": round(wall, 1),
        "first_interval_s": round(first, 1),
        "samples_per_s": round(float(np.median(steady)), 1),
        "losses": {int(k): round(v, 5) for k, v in losses.items()},
    }


def add_eval_arguments(parser: argparse.ArgumentParser, num_tasks: int, rollouts: int) -> None:
    """The flags of a DrawAnything checkpoint evaluated in the script's own process (:func:`evaluated_tasks`): its run,
    the task set and how many of its tasks, rollouts per task, torch threads."""
    parser.add_argument("run", type=Path, help="a DrawAnything training run or checkpoint")
    parser.add_argument("--tasks", default="human")
    parser.add_argument("--num-tasks", type=int, default=num_tasks)
    parser.add_argument("--rollouts", type=int, default=rollouts)
    parser.add_argument("--threads", type=int, default=1)


def evaluated_tasks(args):
    """(checkpoint, benchmark, task set, task indices) of :func:`add_eval_arguments`' flags, with torch on
    ``--threads`` threads."""
    torch.set_num_threads(args.threads)
    ckpt = Checkpoint.load(args.run, use_ema=True)
    return ckpt, *resolve_tasks(args.tasks, ckpt, num_tasks=args.num_tasks, workers=1)


@contextlib.contextmanager
def torch_threads(threads: int):
    """torch on `threads` threads inside the block, its previous count restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def matmul_peak(
    dtype: torch.dtype, threads: int, sizes=(1024, 2048), seconds: float = 1.0, device: str | torch.device = "cpu"
) -> float:
    """This machine's matrix-product rate in GFLOP/s for `dtype` on `threads` torch threads (or on `device`, a GPU):
    the best of square products of `sizes`, each repeated for about `seconds` after a warm-up (the yardstick a
    training rate is set against: what the chip does on the operation that dominates a step)."""
    device = torch.device(device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    best = 0.0
    with torch_threads(threads):
        for n in sizes:
            a, b = (torch.randn(n, n, device=device).to(dtype) for _ in range(2))
            a @ b
            sync()
            count, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                for _ in range(10 if device.type == "cuda" else 1):  # a GPU's products queued ten at a time
                    a @ b
                    count += 1
                sync()
            best = max(best, 2 * n**3 * count / (time.perf_counter() - t0) / 1e9)
    return best


def copy_bandwidth(threads: int, mib: int = 256, seconds: float = 1.0) -> float:
    """This machine's memory bandwidth in GB/s on `threads` torch threads: the best rate of copying one `mib` MiB
    fp32 tensor into another (read and write counted, as STREAM's copy counts them), repeated for about `seconds`
    (the yardstick for memory-bound work such as a parameter update)."""
    best = 0.0
    with torch_threads(threads):
        source, target = torch.ones(mib * 2**18), torch.empty(mib * 2**18)
        target.copy_(source)
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            start = time.perf_counter()
            target.copy_(source)
            best = max(best, 2 * source.nbytes / (time.perf_counter() - start) / 1e9)
    return best


def main_job_flops_per_sample(store: Path, args) -> float:
    """GFLOP of one training window sample (forward and backward, :func:`step_flops`) in the setting of
    :func:`add_main_job_arguments` on `store`, with this checkout's code, averaged over 4 batches (prompts differ
    in length)."""
    opened = EpisodeStore(store)
    model_cfg = get_method("bpp").config(args.preset, args.obs, BENCHMARK)
    model = get_method("bpp").model_cls(model_cfg, opened.stats)
    dataset = PromptBatchDataset(
        opened,
        model.data_spec(),
        frames=BENCHMARK.frames,
        batch_size=args.batch_size,
        num_batches=4,
        tasks_per_batch=args.tasks_per_batch,
    )
    flops = [step_flops(model, to_torch(dataset[i], torch.device("cpu")), amp=False) for i in range(4)]
    return float(np.mean(flops)) / args.batch_size / 1e9


def step_flops(model, batch: dict, amp: bool) -> int:
    """FLOPs (``FlopCounterMode``) of one forward and backward of `model`'s training loss on `batch`, which is on the
    model's device; bf16 autocast there if `amp`. The gradients are cleared after."""
    device = batch["action"].device
    noise = model.draw_noise(batch, torch.Generator(device).manual_seed(0))
    counter = FlopCounterMode(display=False)
    with counter:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            loss = model(batch, noise=noise)
        loss.backward()
    model.zero_grad(set_to_none=True)
    return counter.get_total_flops()


def task_means(results: dict) -> dict[str, float]:
    """Task id -> its mean score, from ``bpp eval``'s results (what ``evaluate`` returns and results.json holds)."""
    return {t["task_id"]: t["score_mean"] for t in results["tasks"]}


def sem(values) -> float:
    """The standard error of the mean of `values` (0 for fewer than two)."""
    values = np.asarray(values, dtype=float)
    return float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0


@dataclass(frozen=True)
class Paired:
    """`b` minus `a`, paired over the tasks both scored: the means, the mean difference and its standard error, and
    the count of tasks on which `b` scores better."""

    tasks: int
    mean_a: float
    mean_b: float
    diff: float
    sem: float
    b_better: int

    def __str__(self) -> str:
        return f"{self.diff:+.2f} ± {self.sem:.2f}"


def paired(a: dict[str, float], b: dict[str, float], lower_is_better: bool = True) -> Paired:
    """`b` minus `a` over the task ids both hold (each a task's score, e.g. its mean over rollouts and seeds)."""
    common = sorted(a.keys() & b.keys())
    if not common:
        raise ValueError("the two evaluations share no task")
    x, y = np.array([a[t] for t in common]), np.array([b[t] for t in common])
    better = (y < x) if lower_is_better else (y > x)
    return Paired(len(common), float(x.mean()), float(y.mean()), float((y - x).mean()), sem(y - x), int(better.sum()))
