"""LIBERO-Gen generation and evaluation with the local executor and with Ray on the same cores: throughput of each,
the overhead ratio, the check that both give the same store and results, and a scaling model to N nodes.

    python bench/ray_overhead.py                              # a Ray instance on this machine, all its cores
    python bench/ray_overhead.py --ray-address HOST:PORT      # a running cluster (its nodes need the same bpp)

Generation: `--tasks` Combination training tasks of the `cpu` preset (state only, 3 demonstrations each).
Evaluation: a debug BPP trained `--train-steps` steps on that store, `--rollouts` rollouts of each of those tasks
(`--max-steps` each). Each executor runs the same jobs from a fresh start (its workers import bpp and LIBERO first,
as in a real run). The anchor outside both executors: the same jobs run one after another in this process, warm
(after one job of each kind, so that imports and first-environment costs are paid), whose mean is what a job costs
when nothing else does; a job's cost on Ray "from outside" is Ray's wall time x CPUs / jobs against that mean (and
the local pool's likewise: what running jobs side by side in fresh workers costs without Ray), and the overhead per
job inside Ray is that wall time x CPUs less the seconds its workers measured in the jobs.
The scaling model uses the per-job seconds measured on Ray: N nodes of C cores make about
N x C x 3600 / (seconds per job + the cluster's overhead per job) x (demonstrations or rollouts per job) an hour,
for many more jobs than cores (the longest job's tail left out).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.benchmark import BENCHMARK
from bpp.benchmarks.libero.dataset import PRESETS, generate
from bpp.checkpoint import Checkpoint
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.executor import Local, Ray
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
from bpp.utils import usable_cores, write_json_atomic


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", type=int, default=6)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--train-steps", type=int, default=20)
    parser.add_argument("--ray-address", default="")
    parser.add_argument("--runs", type=Path, default=Path("runs/ray_overhead"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/ray_overhead.json"))
    args = parser.parse_args()
    import ray

    cores = usable_cores()
    ray.init(address=args.ray_address or None, log_to_driver=False, configure_logging=False)
    cpus = int(ray.cluster_resources().get("CPU", 1))
    nodes = len([n for n in ray.nodes() if n["Alive"]])
    local, on_ray = Local(cores), Ray(args.ray_address, progress=False)
    cfg = replace(PRESETS["cpu"], task_indices=tuple(range(args.tasks)))
    report: dict = {"cores_here": cores, "ray_cpus": cpus, "ray_nodes": nodes, "tasks": args.tasks}

    stores = {}
    for name, executor in (("local", local), ("ray", on_ray)):
        path = args.runs / f"{name}.zarr"
        t0 = time.perf_counter()
        stores[name] = generate(cfg, path, executor, overwrite=True, progress=False)
        seconds = time.perf_counter() - t0
        demos = stores[name].num_episodes
        report[f"generate_{name}"] = {"seconds": round(seconds, 1), "demos": demos,
                                      "demos_per_hour": round(3600 * demos / seconds, 1)}  # fmt: skip
    generation_jobs = [seconds for _, seconds in on_ray.done]
    report["generate_same_store"] = stores["local"].fingerprint() == stores["ray"].fingerprint()

    run = args.runs / "bpp-debug"
    shutil.rmtree(run, ignore_errors=True)
    model_cfg = get_method("bpp").config("debug", "state", BENCHMARK)
    train(TrainConfig(data=stores["local"].path, out=run, method="bpp", steps=args.train_steps, batch_size=8),
          model_cfg, progress=False)  # fmt: skip
    results = {}
    protocol = Protocol(rollouts=args.rollouts, max_steps=args.max_steps)
    for name, executor in (("local", local), ("ray", on_ray)):
        ckpt = Checkpoint.load(run, use_ema=True)
        _, task_set, tasks = resolve_tasks(str(stores["local"].path), ckpt)
        t0 = time.perf_counter()
        results[name] = evaluate(ckpt, task_set, tasks, args.runs / f"eval-{name}", protocol, executor, videos=0,
                                 progress=False, reuse=False)  # fmt: skip
        seconds = time.perf_counter() - t0
        rollouts = len(results[name]["rollouts"])
        report[f"eval_{name}"] = {"seconds": round(seconds, 1), "rollouts": rollouts,
                                  "rollouts_per_hour": round(3600 * rollouts / seconds, 1)}  # fmt: skip
    eval_jobs = [seconds for _, seconds in on_ray.done]
    report["eval_same_results"] = all(results["local"][k] == results["ray"][k] for k in ("summary", "rollouts"))
    warm = warm_job_seconds(cfg, stores["local"], run, protocol, args.runs)
    for what, jobs in (("generate", generation_jobs), ("eval", eval_jobs)):
        wall, local = report[f"{what}_ray"]["seconds"], report[f"{what}_local"]["seconds"]
        per_job = (wall * cpus - sum(jobs)) / len(jobs)  # what the cluster spent beyond the jobs themselves
        report[f"{what}_ray_over_local"] = round(wall / local, 3)
        report[f"{what}_jobs"] = {
            "count": len(jobs),
            "mean_s": round(float(np.mean(jobs)), 2),
            "max_s": round(max(jobs), 2),
            "overhead_per_job_s": round(per_job, 2),
            "warm_in_process_s": round(warm[what], 2),
            "over_warm_per_job_s": round(wall * cpus / len(jobs) - warm[what], 2),
            "local_over_warm_per_job_s": round(local * cores / len(jobs) - warm[what], 2),
        }
        per_job_units = report[f"{what}_ray"]["demos" if what == "generate" else "rollouts"] / len(jobs)
        unit_seconds = (float(np.mean(jobs)) + max(per_job, 0.0)) / per_job_units
        # demonstrations (or rollouts) per hour on n nodes of 16 cores, the longest job's tail left out
        report[f"{what}_model_per_hour"] = {f"{n}x16": round(n * 16 * 3600 / unit_seconds) for n in (1, 4, 16, 64)}
    print(json.dumps(report, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out, report)


def warm_job_seconds(cfg, store, run: Path, protocol, runs: Path) -> dict[str, float]:
    """Mean seconds of a generation job and of an evaluation job run one after another in this process (the local
    executor with one worker), after one job of each kind has run here: the same jobs as the executors', warm."""
    first = replace(cfg, task_indices=cfg.task_indices[:1])
    generate(first, runs / "warm-up.zarr", Local(1), overwrite=True, progress=False)
    t0 = time.perf_counter()
    generate(cfg, runs / "in-process.zarr", Local(1), overwrite=True, progress=False)
    seconds = {"generate": (time.perf_counter() - t0) / len(cfg.task_indices)}
    ckpt = Checkpoint.load(run, use_ema=True)
    _, task_set, tasks = resolve_tasks(str(store.path), ckpt)
    evaluate(
        ckpt, task_set, tasks[:1], runs / "eval-warm-up", protocol, Local(1), videos=0, progress=False, reuse=False
    )
    t0 = time.perf_counter()
    evaluate(ckpt, task_set, tasks, runs / "eval-in-process", protocol, Local(1), videos=0, progress=False, reuse=False)
    seconds["eval"] = (time.perf_counter() - t0) / -(-len(tasks) // protocol.tasks_per_batch)  # per batch of tasks
    return seconds


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main()
