"""Training steps/s of the main job's configuration with the CPU alone and beside busy processes.

    python bench/cpu_threads.py --data data/draw/train-500.zarr [--busy 0 1] [--steps 40]

Each setting trains BPP (the demo's preset, batch 64, 8 tasks per step) in a fresh process for `--steps` steps and
reads the steps/s the training loop logged to TensorBoard (the median over logging intervals after the first, so
start-up is not counted). `--busy N` runs N pure-Python busy loops beside it, as another program on a laptop would.
A setting that makes no progress within `--timeout` seconds is reported as an upper bound. The anchor, measured in
the same run under the same load: the cores' fp32 matrix-product rate on the setting's threads (``matmul_peak``), and
the training's rate as a fraction of it (a step's FLOPs counted once, ``main_job_flops_per_sample``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import main_job_flops_per_sample, matmul_peak

CHILD = """
import json, sys
from pathlib import Path
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
a = json.loads(sys.argv[1])
method = get_method("bpp")
if hasattr(method, "config"):
    from bpp.data.store import EpisodeStore
    from bpp.core.registry import get_benchmark

    cfg = method.config(a["preset"], a["obs"], get_benchmark(EpisodeStore(a["data"]).benchmark))
else:  # before presets were split into sizes and observations
    cfg = method.preset(a["preset"] + "-" + a["obs"])
kw = {k: a[k] for k in ("threads", "workers") if a[k] is not None}
train(TrainConfig(data=Path(a["data"]), out=Path(a["out"]), steps=a["steps"], tasks_per_batch=8, log_every=a["log"],
                  save_every=10**9, keep_checkpoints=1, **kw), cfg, progress=False)
"""


def steps_per_s(run: Path, batch: int = 64) -> list[float]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tb"))
    acc.Reload()
    return [e.value / batch for e in acc.Scalars("train/samples_per_s")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("data/draw/train-500.zarr"))
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--obs", default="board")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--log-every", type=int, default=10)
    parser.add_argument("--busy", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--timeout", type=float, default=240)
    parser.add_argument(
        "--settings",
        nargs="+",
        default=["2,1", "default", "1,1", "2,0", "1,0"],
        help="THREADS,WORKERS pairs, or 'default' for TrainConfig's own defaults",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/cpu_threads.json"))
    args = parser.parse_args()
    batch = argparse.Namespace(preset=args.preset, obs=args.obs, batch_size=64, tasks_per_batch=8)
    step_gflop = 64 * main_job_flops_per_sample(args.data, batch)  # a step of 64 windows, forward and backward
    rows = []
    for busy in args.busy:
        for setting in args.settings:
            threads, workers = (None, None) if setting == "default" else map(int, setting.split(","))
            hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
            try:
                with tempfile.TemporaryDirectory() as tmp:
                    run = Path(tmp) / "run"
                    spec = {
                        "data": str(args.data),
                        "out": str(run),
                        "preset": args.preset,
                        "obs": args.obs,
                        "steps": args.steps,
                        "log": args.log_every,
                        "threads": threads,
                        "workers": workers,
                    }
                    t0 = time.perf_counter()
                    try:
                        subprocess.run(
                            [sys.executable, "-c", CHILD, json.dumps(spec)], check=True, timeout=args.timeout
                        )
                        rates = steps_per_s(run)[1:]
                        rate = sorted(rates)[len(rates) // 2]
                        bound = ""
                    except subprocess.TimeoutExpired:
                        rates = steps_per_s(run) if (run / "tb").exists() else []
                        rate = args.steps / args.timeout if not rates else max(rates)
                        bound = "<"
                    seconds = time.perf_counter() - t0
                peak = matmul_peak(torch.float32, threads) if threads else float("nan")  # under the same load
            finally:
                for h in hogs:
                    h.kill()
            row = {"setting": setting, "busy": busy, "steps_per_s": rate, "bound": bound, "wall_s": seconds}
            row |= {"peak_gflops": peak, "of_peak": rate * step_gflop / peak}
            rows.append(row)
            print(json.dumps(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"a step: {step_gflop:.2f} GFLOP")
    print("| threads,workers | busy processes | steps/s | fp32 matmul GFLOP/s, those threads, same load | of it |")
    print("| --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['setting']} | {r['busy']} | {r['bound']}{r['steps_per_s']:.2f} | {r['peak_gflops']:.1f} | "
              f"{r['of_peak']:.1%} |")  # fmt: skip


if __name__ == "__main__":
    main()
