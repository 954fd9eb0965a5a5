"""Served versus in process: `bpp robot-client` against `bpp serve` scores what `bpp eval` scores.

Trains a small BPP checkpoint (or takes --run), evaluates it in process with `bpp eval`'s protocol, then serves it
and runs the same protocol through the socket (one connection per rollout, all rollouts of a task at once, so the
server batches them), and compares rollout for rollout. `bpp eval` runs a task's rollouts as one batch; the server
batches whichever requests arrive together, so actions agree up to float sums and scores to what those move.

    python bench/serve_vs_eval.py [--run RUN] [--tasks train] [--num-tasks 10] [--rollouts 4]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=None, help="a trained run (default: train a small one)")
    parser.add_argument("--steps", type=int, default=1500, help="training steps of the small run")
    parser.add_argument("--tasks", default="train", help="task set (the server's prompt library too)")
    parser.add_argument("--num-tasks", type=int, default=10)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--client", default="bpp", choices=["bpp", "openpi"])
    args = parser.parse_args()

    from bpp.checkpoint import Checkpoint
    from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
    from bpp.serve.command import build_server
    from bpp.serve.robot import RobotClient, robot_client
    from bpp.serve.server import ServerThread

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run = args.run
        if run is None:
            from bpp.benchmarks.draw.benchmark import BENCHMARK
            from bpp.benchmarks.draw.dataset import PRESETS, generate
            from bpp.policies.registry import get_method
            from bpp.train import TrainConfig, train

            store = generate(PRESETS["debug"], tmp / "train.zarr", workers=1, progress=False)
            run = tmp / "run"
            cfg = TrainConfig(data=store.path, out=run, method="bpp", steps=args.steps, batch_size=32, workers=0)
            train(cfg, get_method("bpp").config("debug", None, BENCHMARK), progress=True)
        ckpt = Checkpoint.load(run, use_ema=True)
        benchmark, task_set, tasks = resolve_tasks(args.tasks, ckpt, num_tasks=args.num_tasks)
        protocol = Protocol(rollouts=args.rollouts)
        t0 = time.perf_counter()
        local = evaluate(ckpt, task_set, tasks, tmp / "eval", protocol, workers=1, videos=0)
        local_s = time.perf_counter() - t0
        server = build_server(run, str(task_set.store.path))
        with ServerThread(server) as url:
            remote = robot_client(
                RobotClient(
                    tasks=task_set.store.path,
                    server=url,
                    num_tasks=args.num_tasks,
                    rollouts=args.rollouts,
                    client=args.client,
                    out=tmp / "robot.json",
                )
            )
    key = lambda row: (row["task"], row["rollout"])  # noqa: E731
    a = {key(r): r for r in local["rollouts"]}
    b = {key(r): r for r in remote["rollouts"]}
    assert a.keys() == b.keys(), "the two runs planned different rollouts"
    diffs = np.array([abs(a[k]["score"] - b[k]["score"]) for k in a])
    same_steps = np.mean([a[k]["steps"] == b[k]["steps"] for k in a])
    metric = benchmark.metric
    print(
        json.dumps(
            {
                "checkpoint": str(ckpt.path),
                "task_set": task_set.label,
                "tasks": len(tasks),
                "rollouts": len(a),
                "in_process": local["summary"]["score_mean"],
                "served": remote["summary"]["score_mean"],
                "max_rollout_score_difference": float(diffs.max()),
                "rollouts_identical_score": float(np.mean(diffs == 0)),
                "rollouts_same_length": float(same_steps),
                "unit": metric.unit,
                "in_process_s": round(local_s, 1),
                "served_s": remote["seconds"],
                "round_trip_ms": remote["round_trip_ms"],
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
