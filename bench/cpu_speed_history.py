"""Is today's code as fast on this CPU as older code? The same `bpp train` run at several commits, alternated.

    python bench/cpu_speed_history.py 43a1c47 HEAD           # the main job's setting (bpp demo), one thread
    python bench/cpu_speed_history.py 43a1c47 HEAD --repeats 3 --steps 400

Each commit is checked out into a git worktree (under ``--work``, removed at the end) and run from there with this
environment's packages (``PYTHONPATH`` points at the worktree's ``src``), so only the project's code differs. The
runs are sequential and alternated (A B A B ...), so a machine that slows down over time slows every commit alike.
Every run trains on the same store, generated once by the current code (the demo's data preset unless ``--tasks``
says otherwise). Reported per run: the median logged samples/s after the first two intervals, the wall time and
the logged losses; at the end, each commit's median rate over its runs and its ratio to the first commit's.

The yardstick is measured in the same call: before each round of runs, the cores' matrix-product rate in fp32 and
bf16 on the runs' thread count (``matmul_peak``), and once the FLOPs of a training sample (this checkout's code; the
commits compared compute the same products), so that each commit's rate is also a fraction of the fp32 peak.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import torch

from common import add_main_job_arguments, main_job_flops_per_sample, matmul_peak, train_rate

REPO = Path(__file__).resolve().parents[1]
PEAK_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}


def git(*arguments: str) -> str:
    return subprocess.run(["git", "-C", str(REPO), *arguments], check=True, capture_output=True, text=True).stdout


def remove_worktree(tree: Path) -> None:
    """Remove the git worktree at `tree` if there is one (never raises: it runs while cleaning up)."""
    subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], capture_output=True)
    subprocess.run(["git", "-C", str(REPO), "worktree", "prune"], capture_output=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("commits", nargs="+", help="git revisions to compare; the first is the reference")
    add_main_job_arguments(parser, steps=300)
    parser.add_argument("--repeats", type=int, default=2, help="runs per commit, alternated")
    parser.add_argument("--data-dir", type=Path, default=Path("data/bench-speed-history"))
    parser.add_argument("--work", type=Path, default=Path("outputs/bench/speed-history-worktrees"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/cpu_speed_history.json"))
    args = parser.parse_args()
    if args.steps < 3 * args.log_every:
        parser.error(
            f"--steps {args.steps} must be at least 3 x --log-every {args.log_every}: rates after two intervals"
        )
    shas = [git("rev-parse", "--short", f"{c}^{{commit}}").strip() for c in args.commits]
    if len(set(shas)) != len(shas):
        parser.error(f"the commits must differ, got {dict(zip(args.commits, shas, strict=True))}")

    from dataclasses import replace

    from bpp.benchmarks.draw import dataset as draw_data
    from bpp.data.store import stored_with

    data_cfg = replace(draw_data.PRESETS["cpu"], num_tasks=args.tasks)
    store = args.data_dir / f"train-{args.tasks}.zarr"
    if stored_with(store, data_cfg) is None:
        draw_data.generate(data_cfg, store, overwrite=True)

    args.work.mkdir(parents=True, exist_ok=True)
    trees = {sha: args.work.resolve() / sha for sha in shas}
    results: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "runs": []}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        for sha, tree in trees.items():
            remove_worktree(tree)  # one a killed run left
            git("worktree", "add", "--detach", "-f", str(tree), sha)
        results["gflop_per_sample"] = main_job_flops_per_sample(store, args)
        results["peaks"] = []
        for repeat in range(args.repeats):
            peak = {name: matmul_peak(dtype, args.threads) for name, dtype in PEAK_DTYPES.items()}
            results["peaks"].append(peak)
            rounded = {k: round(v, 1) for k, v in peak.items()}
            print(json.dumps({"repeat": repeat, "matmul GFLOP/s": rounded}), flush=True)
            for commit, sha in zip(args.commits, shas, strict=True):
                environment = {**os.environ, "PYTHONPATH": str(trees[sha] / "src")}  # the worktree's code
                measured = train_rate(store, args, ["--workers", "0"], env=environment)
                run = {"commit": commit, "sha": sha, "repeat": repeat, **measured}
                results["runs"].append(run)
                args.out.write_text(json.dumps(results, indent=1))  # a run cut short keeps what it measured
                print(json.dumps({k: v for k, v in run.items() if k != "losses"}), flush=True)
    finally:
        for tree in trees.values():  # only the worktrees made here; --work itself only if that leaves it empty
            remove_worktree(tree)
        with contextlib.suppress(OSError):
            args.work.rmdir()

    summary = {}
    fp32_peak = float(np.median([p["fp32"] for p in results["peaks"]]))
    print(
        f"matmul peak on {args.threads} thread(s), median over rounds: "
        + ", ".join(f"{k} {np.median([p[k] for p in results['peaks']]):.1f}" for k in PEAK_DTYPES)
        + f" GFLOP/s; a training sample: {results['gflop_per_sample']:.3f} GFLOP"
    )
    reference = float(np.median([r["samples_per_s"] for r in results["runs"] if r["sha"] == shas[0]]))
    for commit, sha in zip(args.commits, shas, strict=True):
        runs = [r for r in results["runs"] if r["sha"] == sha]
        rate = float(np.median([r["samples_per_s"] for r in runs]))
        same = all(r["losses"] == results["runs"][0]["losses"] for r in runs)
        of_peak = rate * results["gflop_per_sample"] / fp32_peak
        summary[commit] = {
            "sha": sha,
            "samples_per_s": rate,
            "ratio": round(rate / reference, 3),
            "of_fp32_peak": round(of_peak, 3),
            "same_losses": same,
        }
        print(
            f"{commit:>12} ({sha}): {rate:7.1f} samples/s, {rate / reference:.3f}x, {of_peak:.1%} of the fp32 matmul "
            f"peak, losses as the first: {same}"
        )
    results["summary"] = summary
    args.out.write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
