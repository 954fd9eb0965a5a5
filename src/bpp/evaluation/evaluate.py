"""The evaluation protocol for every benchmark, run in parallel over the cores; results as JSON and Markdown.

The protocol follows the paper: for every task, `rollouts` rollouts (32 by default) whose prompts cycle through
the task's demonstrations, each under its own seeded conditions (the benchmark's, e.g. a board angle); a rollout
gets the benchmark's score (e.g. the best distance to the target it reached, or success); scores are averaged per task,
then over tasks. Rollout ``r`` of task ``t`` draws its conditions and seed from ``(seed, t, r)`` alone, so every
method and checkpoint sees the same rollouts.

A control, ``prompts="other-task"``: each rollout is prompted with a demonstration of another task but scored
against its own task's demonstration, as under the paper's protocol. A policy that follows its prompt scores far
worse under it; one that does something generic scores about the same.

A checkpoint is read from disk once (:class:`bpp.checkpoint.Checkpoint`) and handed to the worker processes.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp import __version__
from bpp.benchmarks.contract import Benchmark, TaskSet
from bpp.benchmarks.prompting import run_prompted
from bpp.benchmarks.registry import get_benchmark
from bpp.checkpoint import Checkpoint
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.evaluation.protocol import Protocol, TaskResult, results_json, rollout_rows, summarize
from bpp.utils import read_json, usable_cores, write_json_atomic

__all__ = ["Protocol", "TaskResult", "combine", "evaluate", "resolve_tasks", "run_protocol", "summarize"]


# ------------------------------------------------------------------------------------------- rollouts
_WORKER: dict = {}


def _init_worker(checkpoint: Checkpoint, benchmark: Benchmark, store_path: str, protocol: Protocol, threads: int):
    import torch

    from bpp.policies.agent import PolicyAgent

    # An exception here would make a process pool restart the worker forever: keep it for the first task instead.
    _WORKER.clear()
    try:
        torch.set_num_threads(threads)
        model = checkpoint.build_model()
        _WORKER["agent"] = PolicyAgent(model, record_attention=True, **protocol.agent_options())
        _WORKER["benchmark"] = benchmark
        _WORKER["store"] = EpisodeStore(store_path)
        _WORKER["protocol"] = protocol
    except Exception as err:  # noqa: BLE001 - re-raised by _run_task, in the parent
        _WORKER["error"] = err


def _run_task(job: tuple[int, bool]) -> TaskResult:
    if "error" in _WORKER:
        raise _WORKER["error"]
    task, video = job
    agent, benchmark, store, protocol = (_WORKER[k] for k in ("agent", "benchmark", "store", "protocol"))
    plan = protocol.plan(store, task, benchmark)
    results, attention = run_prompted(
        agent, benchmark, store, plan, protocol.max_steps, [r == 0 for r in range(len(plan))]
    )
    rows = rollout_rows(benchmark, plan, results)
    first = results[0]
    return TaskResult(
        task,
        str(store.tasks[task]["id"]),
        rows,
        last_frame=first.frames[-1] if first.frames else None,
        frames=first.frames if video else None,
        attention=None if attention is None else attention[0],
    )


def run_protocol(
    checkpoint: Checkpoint,
    benchmark: Benchmark,
    store: EpisodeStore,
    tasks: list[int],
    protocol: Protocol,
    workers: int = 0,
    video_tasks: int = 2,
    progress: bool = True,
    desc: str = "eval",
) -> list[TaskResult]:
    """Evaluate `checkpoint` on `tasks` of `store`; tasks are spread over `workers` processes (0: all cores).

    Each process runs a task's rollouts as one batch through one agent, with ``OMP_NUM_THREADS`` torch threads if
    set, else the cores divided among the processes.
    """
    assert protocol.max_steps > 0, "resolve the benchmark's max_steps first (evaluate does)"
    cores = usable_cores()
    workers = max(1, min(workers or cores, len(tasks)))
    jobs = [(t, i < video_tasks) for i, t in enumerate(tasks)]
    # torch threads per worker: OMP_NUM_THREADS if the user set it (e.g. to leave cores to a training run: more
    # threads than free cores slows torch down many times over), else the cores shared among the workers.
    threads = int(os.environ.get("OMP_NUM_THREADS") or 0) or max(1, cores // workers)
    args = (checkpoint, benchmark, str(store.path), protocol, threads)
    bar = tqdm(total=len(tasks) * protocol.rollouts, desc=desc, unit="rollout", disable=not progress)
    out: dict[int, TaskResult] = {}
    if workers == 1:
        _init_worker(*args)
        results = map(_run_task, jobs)
        pool = None
    else:
        # spawn: the parent may already hold torch threads, which fork does not copy safely.
        pool = mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=args)
        results = pool.imap_unordered(_run_task, jobs)
    try:
        for result in results:
            out[result.task] = result
            bar.update(len(result.rollouts))
            bar.set_postfix(score=f"{np.mean([r.mean for r in out.values()]):.2f}")
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    return [out[t] for t in tasks]


def combine(runs: list[dict]) -> dict:
    """Several checkpoints (e.g. seeds) of one method on one task set: mean ± std of their task-averaged scores."""
    values = np.array([run["summary"]["score_mean"] for run in runs])
    return {
        "checkpoints": [run["checkpoint"] for run in runs],
        "score_per_checkpoint": values.tolist(),
        "score_mean": float(values.mean()),
        "score_std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
    }


def load_results(out: Path) -> dict | None:
    """The results recorded in `out`, or None if there are none (or they cannot be read: they get rewritten)."""
    path = out / "results.json"
    if not path.is_file():
        return None
    try:
        data = read_json(path, "results file")
    except UserError as err:
        print(f"[eval] ignoring {err}", file=sys.stderr)
        return None
    return data if isinstance(data, dict) else None


# ------------------------------------------------------------------------------------------- task sets
def resolve_tasks(
    tasks: str,
    checkpoint: Checkpoint,
    files: tuple[Path, ...] = (),
    data_dir: Path | None = None,
    num_tasks: int = 0,
) -> tuple[Benchmark, TaskSet, list[int]]:
    """(benchmark, task set, task indices) to evaluate `checkpoint` on; the benchmark is the checkpoint's own.

    * ``train``: tasks of the store the checkpoint was trained on (50 spread evenly unless `num_tasks`);
    * one of the benchmark's named sets (e.g. ``human``), generated into `data_dir` on first use;
    * a store path: any store of the same benchmark (e.g. a validation split);
    * with `files`: the benchmark's tasks from those files in its file format, demonstrated by its demonstrator.
    """
    benchmark = get_benchmark(checkpoint.benchmark)
    data_dir = Path(data_dir) if data_dir is not None else benchmark.default_data_dir
    if files:
        task_set = benchmark.task_set_from_files(tuple(Path(p) for p in files), data_dir)
    elif tasks == "train":
        task_set = TaskSet(EpisodeStore(checkpoint.state["dataset"]["path"]), "training tasks")
        num_tasks = num_tasks or 50
    elif tasks in benchmark.task_sets:
        task_set = benchmark.task_set(tasks, data_dir)
    elif Path(tasks).exists() or tasks.endswith(".zarr"):
        task_set = TaskSet(EpisodeStore(tasks), f"tasks of {Path(tasks).name}")
    else:
        names = ", ".join(["train", *benchmark.task_sets])
        raise UserError(f"--tasks {tasks!r}: not a task set of {benchmark.name} ({names}) nor a store path")
    store = task_set.store
    if store.benchmark != benchmark.name:
        raise UserError(f"{store.path} holds {store.benchmark} tasks; the checkpoint was trained on {benchmark.name}")
    count = min(num_tasks or store.num_tasks, store.num_tasks)
    chosen = np.unique(np.linspace(0, store.num_tasks - 1, count).round().astype(int)).tolist()
    return benchmark, task_set, chosen


def _overrides(protocol: Protocol) -> str:
    """The agent overrides of `protocol` as a phrase for the report ("" if none)."""
    text = ""
    if protocol.n_action_steps:
        text += f", {protocol.n_action_steps} actions per inference"
    if protocol.inference_steps:
        text += f", {protocol.inference_steps} denoising steps"
    return text


# ------------------------------------------------------------------------------------------- one call
def evaluate(
    checkpoint: Checkpoint | str | Path,
    task_set: TaskSet,
    tasks: list[int],
    out: Path,
    protocol: Protocol = Protocol(),
    workers: int = 0,
    videos: int = 2,
    progress: bool = True,
    reuse: bool = True,
) -> dict:
    """Run the protocol and write ``results.json``, ``results.md``, ``grid.png``, ``attention.png`` and videos
    into `out`. With `reuse`, results already in `out` are returned without running anything if they provably
    match: the same weights (SHA-256 of the file), the same task store content (:meth:`EpisodeStore.fingerprint`),
    the same task indices, the same protocol and the same bpp version.
    """
    from bpp.evaluation import report

    ckpt = checkpoint if isinstance(checkpoint, Checkpoint) else Checkpoint.load(checkpoint, use_ema=True)
    benchmark = get_benchmark(ckpt.benchmark)
    store = task_set.store
    protocol = replace(protocol, max_steps=protocol.max_steps or benchmark.max_steps)
    out = Path(out)
    fingerprint = {"checkpoint_sha256": ckpt.weights_sha256, "tasks_sha256": store.fingerprint(), "bpp": __version__}
    previous = load_results(out)
    if (
        reuse
        and previous is not None
        and previous.get("fingerprint") == fingerprint
        and previous.get("protocol") == asdict(protocol)
        and [t.get("task") for t in previous.get("tasks", [])] == tasks
        and isinstance(previous.get("summary"), dict)
        and "score_mean" in previous["summary"]
    ):
        print(f"[eval] reusing {out / 'results.json'}: same weights, tasks and protocol")
        return previous
    t0 = time.perf_counter()
    results = run_protocol(ckpt, benchmark, store, tasks, protocol, workers, videos, progress, f"eval {task_set.label}")
    metric = benchmark.metric
    meta = {
        "checkpoint": str(ckpt.path),
        "method": ckpt.method,
        "train_step": ckpt.step,
        "benchmark": benchmark.name,
        "metric": asdict(metric),
        "task_set": task_set.label,
        "store": str(store.path),
        "fingerprint": fingerprint,
        "protocol": asdict(protocol),
        "seconds": round(time.perf_counter() - t0, 1),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    out.mkdir(parents=True, exist_ok=True)
    data = results_json(results, meta, metric)
    write_json_atomic(out / "results.json", data)
    s = data["summary"]
    name = f"{ckpt.method} @ step {ckpt.step}"
    title = f"{name} on {task_set.label}: {metric.format(s['score_mean'])}"
    report.write_grid(results, benchmark, store, out / "grid.png", title=title)
    for r in results:
        if r.frames:
            report.write_video(r.frames, out / f"rollout_{report.safe_name(r.task_id)}")
    attended = [r for r in results if r.attention is not None and len(r.attention)]
    if attended:
        n_action_steps = protocol.n_action_steps or ckpt.model_config().horizons.n_action_steps
        report.write_attention(
            attended[0].attention,
            n_action_steps,
            out / "attention.png",
            f"{name}: prompt attention, {attended[0].task_id}",
        )
    rows = [(r.task_id, r.mean, float(np.std([x["score"] for x in r.rollouts])), len(r.rollouts)) for r in results]
    table = report.markdown_table(["task", f"{metric.name} mean", "std over rollouts", "rollouts"], rows)
    good = f"; {100 * s['good_rollouts']:.0f}% of {metric.good_label}" if metric.good_label else ""
    (out / "results.md").write_text(
        f"# {name} on {task_set.label}\n\nCheckpoint `{ckpt.path}`; {s['tasks']} tasks x {protocol.rollouts} "
        f"rollouts, seed {protocol.seed}{_overrides(protocol)}; score: {metric.description}, averaged per task then "
        "over tasks.\n\n"
        f"**{metric.name} {metric.format(s['score_mean'])}** (std over tasks {s['score_std_over_tasks']:.2f}, "
        f"s.e.m. {s['score_sem_over_tasks']:.2f}); median rollout {metric.format(s['score_median_rollout'])}"
        f"{good}. {meta['seconds']:.0f} s.\n\n{table}"
    )
    return data
