"""The DrawAnything-Sim evaluation protocol, run in parallel over the cores; results as JSON and Markdown.

The protocol follows the paper: for every task, `rollouts` rollouts (32 by default) whose prompts cycle through
the task's demonstrations, each on a board at its own seeded angle; a rollout scores the best Chamfer distance it
reached during the episode; scores are averaged per task, then over tasks. Rollout ``r`` of task ``t`` draws its
board angle and seed from ``(seed, t, r)`` alone, so every method and checkpoint sees the same rollouts.

A control, ``prompts="other-task"``: each rollout is prompted with a demonstration of another task but scored
against its own task's demonstration, exactly as before. A policy that follows its prompt scores far worse under
it; one that draws something generic scores about the same.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from bpp.data.store import EpisodeStore
from bpp.envs.draw.geometry import MAX_BOARD_ANGLE
from bpp.utils import write_json_atomic


@dataclass(frozen=True)
class Protocol:
    """Which rollouts are run for each task (identical for every method and checkpoint)."""

    rollouts: int = 32
    """Rollouts per task; prompts cycle through the task's demonstrations."""
    seed: int = 0
    max_steps: int = 400
    prompts: Literal["own", "other-task"] = "own"
    """own: the paper's protocol. other-task: a control; rollout r of task t (of n) is prompted with demonstration
    r mod (its demos) of task (t + 1 + r mod (n - 1)) mod n, never t itself, and scored against t's own."""
    n_action_steps: int = 0
    """Actions executed per inference (0: the checkpoint's Ta)."""
    inference_steps: int = 0
    """Denoising steps per inference of a diffusion decoder (0: the checkpoint's own)."""

    def __post_init__(self):
        if self.prompts not in ("own", "other-task"):
            raise ValueError(f"prompts must be 'own' or 'other-task', got {self.prompts!r}")
        if self.n_action_steps < 0 or self.inference_steps < 0:
            raise ValueError("n_action_steps and inference_steps must be >= 0 (0: the checkpoint's own)")

    def agent_options(self) -> dict:
        """The :class:`~bpp.policies.agent.PolicyAgent` overrides this protocol asks for."""
        return {"n_action_steps": self.n_action_steps or None, "num_inference_steps": self.inference_steps or None}

    def plan(self, store: EpisodeStore, task: int) -> list[dict]:
        """The rollouts of `task`: target episode (whose drawing scores it), prompt episode, board angle and seed."""
        episodes = store.task_episodes()
        if self.prompts == "other-task" and len(episodes) < 2:
            raise ValueError("an other-task prompt control needs a store with at least 2 tasks")
        demos = episodes[task]
        plan = []
        for r in range(self.rollouts):
            rng = np.random.default_rng([self.seed, task, r])
            target = int(demos[r % len(demos)])
            prompt = target
            if self.prompts == "other-task":
                other = episodes[(task + 1 + r % (len(episodes) - 1)) % len(episodes)]
                prompt = int(other[r % len(other)])
            plan.append(
                {
                    "rollout": r,
                    "target_episode": target,
                    "prompt_episode": prompt,
                    "board_angle": float(rng.uniform(-MAX_BOARD_ANGLE, MAX_BOARD_ANGLE)),
                    "seed": int(rng.integers(2**31)),
                }
            )
        return plan


@dataclass
class TaskResult:
    task: int
    task_id: str
    rollouts: list[dict]
    last_frame: np.ndarray | None = field(default=None, repr=False)  # rollout 0, target overlaid
    frames: list | None = field(default=None, repr=False)  # rollout 0's video frames, if asked for
    attention: np.ndarray | None = field(default=None, repr=False)  # rollout 0: (calls, n_chunks + 1)

    @property
    def mean(self) -> float:
        return float(np.mean([r["best_chamfer"] for r in self.rollouts]))


# ------------------------------------------------------------------------------------------- workers
_WORKER: dict = {}


def _init_worker(checkpoint: str, store_path: str, protocol: Protocol, threads: int) -> None:
    import torch

    from bpp.policies.agent import PolicyAgent

    torch.set_num_threads(threads)
    _WORKER["agent"] = PolicyAgent.from_checkpoint(checkpoint, record_attention=True, **protocol.agent_options())
    _WORKER["store"] = EpisodeStore(store_path)
    _WORKER["protocol"] = protocol


def _run_task(job: tuple[int, bool]) -> TaskResult:
    from bpp.evaluation.draw import rollout_batch

    task, video = job
    agent, store, protocol = _WORKER["agent"], _WORKER["store"], _WORKER["protocol"]
    plan = protocol.plan(store, task)
    results = rollout_batch(
        agent,
        store,
        [p["target_episode"] for p in plan],
        [p["board_angle"] for p in plan],
        [p["seed"] for p in plan],
        max_steps=protocol.max_steps,
        record_frames=[r == 0 for r in range(len(plan))],
        prompt_episodes=[p["prompt_episode"] for p in plan],
    )
    rows = [
        {**p, "best_chamfer": r.best_chamfer, "final_chamfer": r.final_chamfer, "steps": r.steps}
        for p, r in zip(plan, results, strict=True)
    ]
    first = results[0]
    return TaskResult(
        task,
        str(store.tasks[task]["id"]),
        rows,
        last_frame=first.frames[-1],
        frames=first.frames if video else None,
        attention=first.attention,
    )


def run_protocol(
    checkpoint: str | Path,
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
    workers = max(1, min(workers or os.cpu_count() or 1, len(tasks)))
    jobs = [(t, i < video_tasks) for i, t in enumerate(tasks)]
    # torch threads per worker: OMP_NUM_THREADS if the user set it (e.g. to leave cores to a training run: more
    # threads than free cores slows torch down many times over), else the cores shared among the workers.
    threads = int(os.environ.get("OMP_NUM_THREADS") or 0) or max(1, (os.cpu_count() or 1) // workers)
    args = (str(checkpoint), str(store.path), protocol, threads)
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
            bar.set_postfix(chamfer=f"{np.mean([r.mean for r in out.values()]):.2f}")
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    return [out[t] for t in tasks]


# ------------------------------------------------------------------------------------------- numbers
def summarize(results: list[TaskResult]) -> dict:
    """Mean over tasks of per-task mean best Chamfer, with the spread over tasks."""
    means = np.array([r.mean for r in results])
    scores = np.array([row["best_chamfer"] for r in results for row in r.rollouts])
    return {
        "chamfer_mean": float(means.mean()),
        "chamfer_std_over_tasks": float(means.std()),
        "chamfer_sem_over_tasks": float(means.std(ddof=1) / np.sqrt(len(means))) if len(means) > 1 else 0.0,
        "chamfer_median_rollout": float(np.median(scores)),
        "rollouts_under_5px": float(np.mean(scores < 5.0)),
        "tasks": len(results),
        "rollouts": int(scores.size),
    }


def results_json(results: list[TaskResult], meta: dict) -> dict:
    return {
        **meta,
        "summary": summarize(results),
        "tasks": [{"task": r.task, "task_id": r.task_id, "chamfer_mean": r.mean} for r in results],
        "rollouts": [{"task": r.task, "task_id": r.task_id, **row} for r in results for row in r.rollouts],
    }


def combine(runs: list[dict]) -> dict:
    """Several checkpoints (e.g. seeds) of one method on one task set: mean ± std of their task-averaged scores."""
    values = np.array([run["summary"]["chamfer_mean"] for run in runs])
    return {
        "checkpoints": [run["checkpoint"] for run in runs],
        "chamfer_per_checkpoint": values.tolist(),
        "chamfer_mean": float(values.mean()),
        "chamfer_std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
    }


def write_results(results: list[TaskResult], meta: dict, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    data = results_json(results, meta)
    write_json_atomic(out / "results.json", data)
    return data


def load_results(out: Path) -> dict | None:
    path = out / "results.json"
    return json.loads(path.read_text()) if path.is_file() else None


def protocol_meta(checkpoint: Path, store: EpisodeStore, task_set: str, protocol: Protocol, seconds: float) -> dict:
    from bpp.checkpoint import read_state, resolve_checkpoint

    ckpt = resolve_checkpoint(checkpoint)
    state = read_state(ckpt)
    return {
        "checkpoint": str(ckpt),
        "method": state["method"],
        "train_step": int(state["step"]),
        "task_set": task_set,
        "store": str(store.path),
        "protocol": asdict(protocol),
        "seconds": round(seconds, 1),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }


# ------------------------------------------------------------------------------------------- task sets
def resolve_task_set(
    tasks: str,
    checkpoint: Path,
    drawings: tuple[Path, ...] = (),
    data_dir: Path = Path("data/draw"),
    num_tasks: int = 0,
) -> tuple[EpisodeStore, list[int], str]:
    """(store, task indices, label) for a task set name.

    * ``human``: the 50 built-in unseen human-made drawings (generated into `data_dir` on first use);
    * ``train``: tasks of the store the checkpoint was trained on (50 spread evenly unless `num_tasks`);
    * a store path: any DrawAnything store (e.g. a validation split of procedural tasks);
    * with `drawings` (JSON stroke files or SVG): those drawings, demonstrated by the built-in demonstrator.
    """
    from bpp.envs.draw.dataset import PRESETS, DrawDataConfig, generate

    if drawings:
        cfg = DrawDataConfig(source="files", drawings=tuple(Path(p) for p in drawings))
        key = hashlib.sha1("\n".join(str(Path(p).resolve()) for p in drawings).encode()).hexdigest()[:10]
        store = generate(cfg, Path(data_dir) / f"files-{key}.zarr", overwrite=True, progress=False)
        label = "drawings: " + ", ".join(Path(p).name for p in drawings)
    elif tasks == "human":
        path = Path(data_dir) / "human.zarr"
        store = _open_or_generate(path, lambda: generate(PRESETS["human"], path, overwrite=True))
        label = "unseen human-made drawings"
    elif tasks == "train":
        config = json.loads((_run_dir(checkpoint) / "config.json").read_text())
        store = EpisodeStore(config["dataset"]["path"])
        num_tasks = num_tasks or 50
        label = "training drawings"
    else:
        store = EpisodeStore(tasks)
        label = f"tasks of {Path(tasks).name}"
    count = min(num_tasks or store.num_tasks, store.num_tasks)
    chosen = np.unique(np.linspace(0, store.num_tasks - 1, count).round().astype(int)).tolist()
    return store, chosen, label


def _open_or_generate(path: Path, make) -> EpisodeStore:
    from bpp.data.store import StoreError

    try:
        return EpisodeStore(path)
    except StoreError:
        return make()


def _overrides(protocol: Protocol) -> str:
    """The agent overrides of `protocol` as a phrase for the report ("" if none)."""
    text = ""
    if protocol.n_action_steps:
        text += f", {protocol.n_action_steps} actions per inference"
    if protocol.inference_steps:
        text += f", {protocol.inference_steps} denoising steps"
    return text


def _run_dir(checkpoint: Path) -> Path:
    from bpp.checkpoint import resolve_checkpoint

    ckpt = resolve_checkpoint(checkpoint)
    return ckpt.parent.parent  # <run>/checkpoints/step_N


# ------------------------------------------------------------------------------------------- one call
def _same_protocol(recorded: dict | None, protocol: Protocol) -> bool:
    """Whether results recorded under `recorded` were run with `protocol` (fields added since default as before)."""
    try:
        return recorded is not None and Protocol(**recorded) == protocol
    except TypeError:  # a field this version does not know
        return False


def evaluate(
    checkpoint: Path,
    store: EpisodeStore,
    tasks: list[int],
    label: str,
    out: Path,
    protocol: Protocol = Protocol(),
    workers: int = 0,
    videos: int = 2,
    progress: bool = True,
    reuse: bool = True,
) -> dict:
    """Run the protocol and write ``results.json``, ``results.md``, ``grid.png``, ``attention.png`` and videos
    into `out`. With `reuse`, results already in `out` for the same checkpoint, store, tasks and protocol are
    returned without running anything.
    """
    from bpp.checkpoint import resolve_checkpoint
    from bpp.evaluation import report

    out = Path(out)
    ckpt = resolve_checkpoint(checkpoint)
    previous = load_results(out)
    if (
        reuse
        and previous is not None
        and previous.get("checkpoint") == str(ckpt)
        and previous.get("store") == str(store.path)
        and _same_protocol(previous.get("protocol"), protocol)
        and [t["task"] for t in previous["tasks"]] == tasks
    ):
        print(f"[eval] reusing {out / 'results.json'}")
        return previous
    t0 = time.perf_counter()
    results = run_protocol(ckpt, store, tasks, protocol, workers, videos, progress, desc=f"eval {label}")
    meta = protocol_meta(ckpt, store, label, protocol, time.perf_counter() - t0)
    data = write_results(results, meta, out)
    s = data["summary"]
    name = f"{meta['method']} @ step {meta['train_step']}"
    report.write_grid(results, store, out / "grid.png", title=f"{name} on {label}: {s['chamfer_mean']:.2f} px")
    for r in results:
        if r.frames:
            report.write_video(r.frames, out / f"rollout_{r.task_id}")
    attended = [r for r in results if r.attention is not None and len(r.attention)]
    if attended:
        from bpp.checkpoint import read_state

        n_action_steps = protocol.n_action_steps or read_state(ckpt)["model_config"]["horizons"]["n_action_steps"]
        report.write_attention(
            attended[0].attention,
            n_action_steps,
            out / "attention.png",
            f"{name}: prompt attention, {attended[0].task_id}",
        )
    rows = [
        (r.task_id, r.mean, float(np.std([x["best_chamfer"] for x in r.rollouts])), len(r.rollouts)) for r in results
    ]
    table = report.markdown_table(["task", "Chamfer mean (px)", "std over rollouts", "rollouts"], rows)
    (out / "results.md").write_text(
        f"# {name} on {label}\n\nCheckpoint `{ckpt}`; {s['tasks']} tasks x {protocol.rollouts} rollouts, "
        f"seed {protocol.seed}{_overrides(protocol)}; best Chamfer per rollout (px at 512), averaged per task then "
        "over tasks.\n\n"
        f"**Chamfer {s['chamfer_mean']:.2f} px** (std over tasks {s['chamfer_std_over_tasks']:.2f}, "
        f"s.e.m. {s['chamfer_sem_over_tasks']:.2f}); median rollout {s['chamfer_median_rollout']:.2f} px; "
        f"{100 * s['rollouts_under_5px']:.0f}% of rollouts under 5 px. {meta['seconds']:.0f} s.\n\n{table}"
    )
    return data
