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

from common import add_main_job_arguments, train_rate


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
