"""What `bpp train --compile` buys on this machine: the same run eager and compiled, alternated.

    python bench/compile_speed.py                                  # the main job's setting (bpp demo), 1 thread
    python bench/compile_speed.py --preset debug --obs board --steps 60 --tasks 40    # a quick check

Each run is `bpp train` as a subprocess, on a procedural DrawAnything store generated first (the demo's data
preset). Reported per run: the wall time, the time to the first logged interval (which holds the compilation), the
median logged samples/s after the first two intervals, and the logged losses; at the end, the ratio of the compiled
runs' median rate to the eager runs', and the largest difference between their losses at the same step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gpu_throughput import train_subprocess  # this folder's script, on the path when run as a script


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_main_job_arguments(parser, steps=400)
    parser.add_argument("--mode", default="default", help="the compiled runs' --compile mode")
    parser.add_argument("--repeats", type=int, default=2, help="eager/compiled pairs, alternated")
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-compile"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/compile_speed.json"))
    args = parser.parse_args()

    from bpp.benchmarks.draw import dataset as draw_data

    store = args.data_dir / f"procedural-{args.tasks}.zarr"
    if not (store / "zarr.json").exists():
        draw_data.generate(replace(draw_data.DrawDataConfig(), num_tasks=args.tasks), store, overwrite=True)
    results = []
    for _ in range(args.repeats):
        for mode in ("off", args.mode):
            results.append({"mode": mode, **train_rate(store, args, ["--compile", mode])})
            print(json.dumps({k: v for k, v in results[-1].items() if k != "losses"}), flush=True)
    eager = [r for r in results if r["mode"] == "off"]
    fast = [r for r in results if r["mode"] != "off"]
    summary = {
        "command": " ".join(sys.argv),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "speedup": round(
            np.median([r["samples_per_s"] for r in fast]) / np.median([r["samples_per_s"] for r in eager]), 3
        ),
        "max_loss_difference": max(
            abs(a["losses"][s] - b["losses"][s]) for a in eager for b in fast for s in a["losses"] if s in b["losses"]
        ),
        "runs": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "runs"}, indent=1))


if __name__ == "__main__":
    main()
