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

import contextlib
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from bpp import __version__
from bpp.checkpoint import Checkpoint
from bpp.core.contract import Benchmark, TaskSet
from bpp.core.prompting import run_prompted
from bpp.core.registry import get_benchmark
from bpp.data.contexts import check_edit_applies
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.evaluation import report
from bpp.evaluation.protocol import Protocol, TaskResult, results_json, rollout_rows, summarize
from bpp.executor import Executor, as_executor, local_path
from bpp.policies.agent import PolicyAgent
from bpp.policies.registry import get_method
from bpp.utils import (
    atomic_path,
    file_stem,
    journal_folder,
    read_json,
    remove_stale_partials,
    write_json_atomic,
    write_text_atomic,
)

__all__ = ["Protocol", "TaskResult", "combine", "evaluate", "resolve_tasks", "run_protocol", "summarize"]


# ------------------------------------------------------------------------------------------- rollouts
_WORKER: dict = {}


def _init_worker(checkpoint: Checkpoint, benchmark: Benchmark, store_folder, protocol: Protocol, threads: int):
    # An exception here would make a process pool restart the worker forever: keep it for the first task instead.
    _WORKER.clear()
    try:
        torch.set_num_threads(threads)
        model = checkpoint.build_model()
        _WORKER["agent"] = PolicyAgent(model, record_attention=True, **protocol.agent_options())
        _WORKER["benchmark"] = benchmark
        _WORKER["store"] = EpisodeStore(local_path(store_folder), benchmark.derived_keys)
        _WORKER["protocol"] = protocol
    except Exception as err:  # noqa: BLE001 - re-raised by _run_tasks, in the parent
        _WORKER["error"] = err


def _run_tasks(job: tuple[tuple[int, bool], ...]) -> list[TaskResult]:
    """The rollouts of a batch of tasks ((task, video) pairs), stepping together through one agent."""
    if "error" in _WORKER:
        raise _WORKER["error"]
    agent, benchmark, store, protocol = (_WORKER[k] for k in ("agent", "benchmark", "store", "protocol"))
    plans = [protocol.plan(store, task, benchmark) for task, _ in job]
    # A task's first rollout's final frame goes into the report's grid; all of its frames only into a video.
    record = [
        ("all" if video else "last") if r == 0 else False
        for (_, video), plan in zip(job, plans, strict=True)
        for r in range(len(plan))
    ]
    plan = [row for task_plan in plans for row in task_plan]
    results, attention = run_prompted(agent, benchmark, store, plan, protocol.max_steps, record)
    out, start = [], 0
    for (task, video), task_plan in zip(job, plans, strict=True):
        mine = results[start : start + len(task_plan)]
        first = mine[0]
        out.append(
            TaskResult(
                task,
                str(store.tasks[task]["id"]),
                rollout_rows(benchmark, task_plan, mine),
                last_frame=first.frames[-1] if first.frames else None,
                frames=first.frames if video else None,
                attention=None if attention is None else attention[start],
            )
        )
        start += len(task_plan)
    return out


def run_protocol(
    checkpoint: Checkpoint,
    benchmark: Benchmark,
    store: EpisodeStore,
    tasks: list[int],
    protocol: Protocol,
    workers: int | Executor = 0,
    video_tasks: int = 2,
    progress: bool = True,
    desc: str = "eval",
    journal: Journal | None = None,
) -> list[TaskResult]:
    """Evaluate `checkpoint` on `tasks` of `store`; tasks are spread over `workers` processes (0: all cores) or an
    :class:`~bpp.executor.Executor` (e.g. a Ray cluster, whose nodes get the store's contents).

    Each worker runs the rollouts of ``protocol.tasks_per_batch`` consecutive tasks of `tasks` as one batch through
    one agent (so results do not depend on where a task runs), with ``OMP_NUM_THREADS`` torch threads if set, else
    the cores it has to itself. With a `journal`, the tasks it holds are not run again (a batch runs whole if any of
    its tasks is missing), and every task that finishes is added to it.
    """
    assert protocol.max_steps > 0, "resolve the benchmark's max_steps first (evaluate does)"
    out: dict[int, TaskResult] = journal.load() if journal is not None else {}
    executor = as_executor(workers)
    size = protocol.tasks_per_batch
    batches = [[(t, i < video_tasks) for i, t in enumerate(tasks)][b : b + size] for b in range(0, len(tasks), size)]
    jobs = [tuple(batch) for batch in batches if any(t not in out for t, _ in batch)]
    rerun = {t for job in jobs for t, _ in job}
    out = {t: result for t, result in out.items() if t not in rerun}  # a batch's tasks run (and count) together
    args = (checkpoint, benchmark, executor.share(store.path), protocol, executor.threads(len(jobs)))
    bar = tqdm(total=len(tasks) * protocol.rollouts, initial=len(out) * protocol.rollouts, desc=desc, unit="rollout",
               disable=not progress)  # fmt: skip
    # spawned workers: this process may already hold torch threads, which fork does not copy safely.
    results = executor.map(_run_tasks, jobs, initializer=_init_worker, initargs=args, start_method="spawn")
    with bar, contextlib.closing(results):
        for batch in results:
            for result in batch:
                if journal is not None:
                    journal.add(result)
                out[result.task] = result
                bar.update(len(result.rollouts))
            bar.set_postfix(score=f"{np.mean([r.mean for r in out.values()]):.2f}")
    return [out[t] for t in tasks]


class Journal:
    """The finished tasks of an evaluation into `out`, kept beside it (``.<out>.journal/``) until its results are
    written, so that the same command run again after an interruption (Ctrl-C, a killed process or machine) runs only
    the tasks that are missing. It belongs to one evaluation (`key`: weights, tasks, protocol); another one's is
    discarded. Each task is one ``.npz`` file (JSON and arrays, no pickles), written atomically."""

    def __init__(self, out: Path, key: dict):
        self.out, self.key = out, key
        self.folder = journal_folder(out, key, create=False)  # made when the first task is done

    def load(self) -> dict[int, TaskResult]:
        found = {}
        for path in sorted(self.folder.glob("task-*.npz")):
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                arrays = {k: data[k] for k in ("last_frame", "frames", "attention") if k in data.files}
            frames = arrays.get("frames")
            result = TaskResult(meta["task"], meta["task_id"], meta["rollouts"], arrays.get("last_frame"),
                                None if frames is None else list(frames), arrays.get("attention"))  # fmt: skip
            found[result.task] = result
        if found:
            print(f"[eval] resuming: {len(found)} tasks already evaluated ({self.folder})")
        return found

    def add(self, result: TaskResult) -> None:
        if not self.folder.is_dir():
            journal_folder(self.out, self.key)
        arrays = {"last_frame": result.last_frame, "attention": result.attention}
        if result.frames is not None:
            arrays["frames"] = np.stack(result.frames)
        meta = {"task": result.task, "task_id": result.task_id, "rollouts": result.rollouts}
        with atomic_path(self.folder / f"task-{result.task:05d}.npz") as tmp:
            np.savez(tmp, meta=json.dumps(meta), **{k: v for k, v in arrays.items() if v is not None})

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


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


def missing_outputs(out: Path, results: dict) -> list[str]:
    """The files `results` records as written into `out` (``outputs``: name -> bytes) that are not there whole. A
    record without ``outputs`` (an older bpp's) cannot vouch for its files: it counts as missing them all."""
    outputs = results.get("outputs")
    if not isinstance(outputs, dict) or not outputs:
        return ["(no record of the outputs)"]
    missing = []
    for name, size in outputs.items():
        path = out / str(name)
        if Path(str(name)).name != str(name) or not path.is_file() or path.stat().st_size != size:
            missing.append(str(name))
    return missing


def video_stems(task_ids: list[str]) -> dict[str, str]:
    """Each task id -> the stem of its rollout video's file (``rollout_<file_stem(id)>``), one per id."""
    stems = {task_id: f"rollout_{file_stem(task_id)}" for task_id in task_ids}
    assert len(set(stems.values())) == len(stems), "file_stem gave two ids one name"
    return stems


def check_output_folder(out: Path) -> None:
    """Refuse `out` before any rollout runs if the results could not be written there: a file, or under one, or in
    a folder this process may not write to."""
    out = Path(out)
    folder = out
    while not os.path.lexists(folder) and folder.parent != folder:
        folder = folder.parent
    if not folder.is_dir():
        raise UserError(f"--out {out}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"--out {out}: {folder} is not writable")


# ------------------------------------------------------------------------------------------- task sets
def resolve_tasks(
    tasks: str,
    checkpoint: Checkpoint,
    files: tuple[Path, ...] = (),
    data_dir: Path | None = None,
    num_tasks: int = 0,
    workers: int = 0,
    flag: str = "--tasks",
) -> tuple[Benchmark, TaskSet, list[int]]:
    """(benchmark, task set, task indices) to evaluate `checkpoint` on; the benchmark is the checkpoint's own.

    * ``train``: tasks of the store the checkpoint was trained on (50 spread evenly unless `num_tasks`);
    * one of the benchmark's named sets (e.g. ``human``), generated into `data_dir` on first use;
    * a store path: any store of the same benchmark (e.g. a validation split);
    * with `files`: the benchmark's tasks from those files in its file format, demonstrated by its demonstrator.

    A task set generated here is demonstrated over `workers` processes (0: one per core). Errors name `tasks` as
    the command's `flag`. The task set's store is
    opened with the benchmark's derived keys, as training opened its own.
    """
    benchmark = get_benchmark(checkpoint.benchmark)
    data_dir = Path(data_dir) if data_dir is not None else benchmark.default_data_dir
    if files:
        task_set = benchmark.task_set_from_files(tuple(Path(p) for p in files), data_dir, workers)
    elif tasks == "train":
        task_set = TaskSet(EpisodeStore(checkpoint.state["dataset"]["path"]), "training tasks")
        num_tasks = num_tasks or 50
    elif tasks in benchmark.task_sets:
        task_set = benchmark.task_set(tasks, data_dir, workers)
    elif Path(tasks).exists() or tasks.endswith(".zarr"):
        task_set = TaskSet(EpisodeStore(tasks), f"tasks of {Path(tasks).name}")
    else:
        names = ", ".join(["train", *benchmark.task_sets])
        raise UserError(f"{flag} {tasks!r}: not a task set of {benchmark.name} ({names}) nor a store path")
    if task_set.store.benchmark != benchmark.name:
        holds = task_set.store.benchmark
        raise UserError(
            f"{flag} {task_set.store.path} holds {holds} tasks; the checkpoint was trained on {benchmark.name}"
        )
    store = EpisodeStore(task_set.store.path, benchmark.derived_keys)  # as the benchmark presents it
    task_set = replace(task_set, store=store)
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
    if protocol.noise_scale is not None:
        text += f", the decoder's noise x {protocol.noise_scale:g}"
    if protocol.tasks_per_batch > 1:
        text += f", {protocol.tasks_per_batch} tasks a batch"
    return text


# ------------------------------------------------------------------------------------------- one call
RECORDED_BEFORE = {"tasks_per_batch": 1}
"""The protocol fields results recorded before those fields existed were evaluated with."""


def evaluate(
    checkpoint: Checkpoint | str | Path,
    task_set: TaskSet,
    tasks: list[int],
    out: Path,
    protocol: Protocol = Protocol(),
    workers: int | Executor = 0,
    videos: int = 2,
    progress: bool = True,
    reuse: bool = True,
) -> dict:
    """Run the protocol and write ``results.json``, ``results.md``, ``grid.png``, ``attention.png`` and videos
    into `out`. With `reuse`, results already in `out` are returned without running anything if they provably
    match: the same weights (SHA-256 of the file), the same task store content (:meth:`EpisodeStore.fingerprint`),
    the same task indices, the same protocol and the same bpp version, and every file they record is there whole.

    Every file is written complete or not at all (:func:`bpp.utils.atomic_path`), and ``results.json``, which
    records them (``outputs``: name -> bytes), last: an evaluation stopped by a full disk, Ctrl-C or SIGTERM leaves
    nothing that a rerun would reuse. A task's video is named from its id by :func:`bpp.utils.file_stem` (one name
    per id), and the names and the folder are checked before any rollout runs.
    """
    ckpt = checkpoint if isinstance(checkpoint, Checkpoint) else Checkpoint.load(checkpoint, use_ema=True)
    benchmark = get_benchmark(ckpt.benchmark)
    store = task_set.store
    protocol = replace(protocol, max_steps=protocol.max_steps or benchmark.max_steps)
    check_edit_applies(get_method(ckpt.method).model_cls.context_kind, protocol.prompts)  # before any rollout
    out = Path(out)
    fingerprint = {"checkpoint_sha256": ckpt.weights_sha256, "tasks_sha256": store.fingerprint(), "bpp": __version__}
    previous = load_results(out)
    if (
        reuse
        and previous is not None
        and previous.get("fingerprint") == fingerprint
        and isinstance(previous.get("protocol"), dict)
        and {**RECORDED_BEFORE, **previous["protocol"]} == asdict(protocol)
        and [t.get("task") for t in previous.get("tasks", [])] == tasks
        and isinstance(previous.get("summary"), dict)
        and "score_mean" in previous["summary"]
    ):
        missing = missing_outputs(out, previous)
        if not missing:
            print(f"[eval] reusing {out / 'results.json'}: same weights, tasks and protocol")
            return previous
        print(f"[eval] not reusing {out / 'results.json'}: missing or incomplete {', '.join(missing)}", file=sys.stderr)
    check_output_folder(out)
    video_names = video_stems([str(store.tasks[t]["id"]) for t in tasks[:videos]])  # before any rollout runs
    t0 = time.perf_counter()
    journal = Journal(out, {**fingerprint, "protocol": asdict(protocol), "tasks": tasks, "videos": videos})
    label = f"eval {task_set.label}"
    results = run_protocol(ckpt, benchmark, store, tasks, protocol, workers, videos, progress, label, journal)
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
    remove_stale_partials(out)
    # The record goes first and comes back last: files of this evaluation and of an earlier one are never mixed
    # under a record that vouches for them.
    (out / "results.json").unlink(missing_ok=True)
    written: dict[str, int] = {}

    def wrote(path: Path) -> None:
        written[path.name] = path.stat().st_size

    data = results_json(results, meta, metric)
    s = data["summary"]
    name = f"{ckpt.method} @ step {ckpt.step}"
    title = f"{name} on {task_set.label}: {metric.format(s['score_mean'])}"
    wrote(report.write_grid(results, benchmark, store, out / "grid.png", title=title))
    video_files = {}
    for r in results:
        if r.frames:
            path = report.write_video(r.frames, out / video_names[r.task_id])
            wrote(path)
            video_files[r.task_id] = path.name
    attended = [r for r in results if r.attention is not None and len(r.attention)]
    if attended:
        n_action_steps = protocol.n_action_steps or ckpt.model_config().horizons.n_action_steps
        path = report.write_attention(
            attended[0].attention,
            n_action_steps,
            out / "attention.png",
            f"{name}: prompt attention, {attended[0].task_id}",
        )
        wrote(path)
    rows = [(r.task_id, r.mean, float(np.std([x["score"] for x in r.rollouts])), len(r.rollouts)) for r in results]
    table = report.markdown_table(["task", f"{metric.name} mean", "std over rollouts", "rollouts"], rows)
    good = f"; {100 * s['good_rollouts']:.0f}% of {metric.good_label}" if metric.good_label else ""
    write_text_atomic(
        out / "results.md",
        f"# {name} on {task_set.label}\n\nCheckpoint `{ckpt.path}`; {s['tasks']} tasks x {protocol.rollouts} "
        f"rollouts, seed {protocol.seed}{_overrides(protocol)}; score: {metric.description}, averaged per task then "
        "over tasks.\n\n"
        f"**{metric.name} {metric.format(s['score_mean'])}** (std over tasks {s['score_std_over_tasks']:.2f}, "
        f"s.e.m. {s['score_sem_over_tasks']:.2f}); median rollout {metric.format(s['score_median_rollout'])}"
        f"{good}. {meta['seconds']:.0f} s.\n\n{table}",
    )
    wrote(out / "results.md")
    data["outputs"] = written
    for row in data["tasks"]:
        row["video"] = video_files.get(row["task_id"])
    write_json_atomic(out / "results.json", data)
    journal.remove()
    return data
