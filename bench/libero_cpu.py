"""LIBERO-Gen Combination at CPU scale: BPP against Goal-Image, Language and ICRT on the 10 held-out tasks, with the
same data, observation preset (`state`: proprioception + object poses, not the paper's cameras), budget and seeds.

    python bench/libero_cpu.py --prepare-only                   # the training store and the held-out tasks, once
    OMP_NUM_THREADS=1 python bench/libero_cpu.py --lane 0 --lanes 2 &     # two one-thread lanes on the 2 cores
    OMP_NUM_THREADS=1 python bench/libero_cpu.py --lane 1 --lanes 2 &
    python bench/libero_cpu.py --report-only                    # table + chart from whatever has been evaluated

Data: the `cpu` data preset (every Combination training task x 3 scripted demonstrations, state only; about an
hour to generate on 2 cores) and the `held-out` task set (the 10 held-out tasks x 5 demonstrations, the prompts).
Each method trains `--steps` steps of its `cpu` size preset with one thread, then is evaluated with the paper's
protocol (success by LIBERO's predicates, at most 550 steps, each rollout from its own initial state) on the
held-out tasks and on --train-tasks training tasks. Re-running reuses finished stores, runs and evaluations and
resumes killed training.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bpp.checkpoint import Checkpoint
from bpp.data.store import stored_with
from bpp.envs.libero.benchmark import BENCHMARK
from bpp.envs.libero.dataset import PRESETS, generate
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import bar_chart, markdown_table
from bpp.policies.registry import get_method
from bpp.utils import write_json_atomic
from draw_ablations import per_drawing
from draw_cpu_benchmark import NAMES, add_budget_arguments, budgets, train_run

PAPER = {"goal_image": (59.1, 47.9), "language": (80.0, 69.9), "bpp": (88.4, 79.1)}
"""The paper's Combination success rates (%), training tasks / unseen tasks (cameras, GPUs, 3 seeds)."""


def training_store(args):
    """The training store of --data-preset (`cpu`: the one `bpp libero generate --preset cpu` writes by default)."""
    name = "combination-train" if args.data_preset == "cpu" else f"combination-train-{args.data_preset}"
    path = args.data_dir / f"{name}.zarr"
    store = stored_with(path, PRESETS[args.data_preset])
    if store is None:
        store = generate(PRESETS[args.data_preset], path, workers=args.workers, overwrite=path.exists())
    return store


def run_method(method: str, seed: int, args) -> None:
    store = training_store(args)
    run = args.runs / f"{method}-s{seed}"
    model_cfg = get_method(method).config("cpu", "state", BENCHMARK)
    steps, batch = args.method_steps[method], args.method_batch[method]
    seconds = train_run(method, "cpu", "state", store, run, steps, seed, batch_size=batch, tasks_per_batch=8,
                        threads=1, model_cfg=model_cfg)  # fmt: skip
    write_json_atomic(run / "train.json", {"train_s": seconds, "steps": steps, "batch": batch})
    checkpoint = Checkpoint.load(run, use_ema=True)
    for name, tasks, count, rollouts in (
        ("held-out", "held-out", 0, args.rollouts),
        ("train", "train", args.train_tasks, args.train_rollouts),
    ):
        protocol = Protocol(rollouts=rollouts, seed=seed)
        _, task_set, indices = resolve_tasks(tasks, checkpoint, data_dir=args.data_dir, num_tasks=count)
        evaluate(checkpoint, task_set, indices, args.out / f"{method}-s{seed}" / name, protocol, workers=1, videos=2)


def _lifted(out: Path, method: str, seeds) -> str:
    """How often held-out rollouts lifted the bowl their goal moves, and any other object (% of rollouts; evaluations
    run before rollouts recorded it show a dash)."""
    rows = []
    for seed in seeds:
        path = out / f"{method}-s{seed}" / "held-out" / "results.json"
        if path.is_file():
            rows += json.loads(path.read_text())["rollouts"]
    if not rows or "lifted" not in rows[0]:
        return "-"
    return " / ".join(f"{100 * np.mean([r[key] for r in rows]):.0f}" for key in ("lifted", "lifted_other"))


def report(args) -> str:
    rows, chart = [], {}
    for method in args.methods:
        cells = []
        for split in ("train", "held-out"):
            seeds = [per_drawing(args.out / f"{method}-s{s}" / split / "results.json") for s in args.seeds]
            seeds = [s for s in seeds if s]
            if not seeds:
                cells.append("not run yet")
                continue
            x = 100 * np.array([np.mean(list(s.values())) for s in seeds])
            tasks = 100 * np.array([np.mean([s[t] for s in seeds]) for t in seeds[0]])
            se = tasks.std(ddof=1) / np.sqrt(len(tasks)) if len(tasks) > 1 else 0.0
            cells.append(f"{x.mean():.1f} ± {se:.1f} ({len(tasks)} tasks)")
            chart.setdefault(f"{split} tasks", {})[NAMES[method]] = (float(x.mean()), float(se))
        cells.append(_lifted(args.out, method, args.seeds))
        trained = [
            json.loads((args.runs / f"{method}-s{s}" / "train.json").read_text())
            for s in args.seeds
            if (args.runs / f"{method}-s{s}" / "train.json").is_file()
        ]
        minutes = [t["train_s"] / 60 for t in trained]
        budget = f"{trained[0]['steps']} x {trained[0].get('batch', 64)}" if trained else "-"
        paper = PAPER.get(method)
        rows.append(
            (
                NAMES[method],
                *cells,
                f"{paper[0]} / {paper[1]}" if paper else "-",
                budget,
                f"{np.mean(minutes):.0f}" if minutes else "-",
            )
        )
    header = ["method", "training tasks (%)", "held-out tasks (%)", "held-out: lifted its bowl / another object (%)",
              "paper: train / unseen (%)", "steps x batch",
              "train min"]  # fmt: skip
    text = (
        f"LIBERO-Gen Combination, `state` observations (not the paper's cameras), `cpu` size presets trained with "
        f"one thread, seeds {args.seeds}, {args.rollouts} rollouts per held-out task and {args.train_rollouts} per "
        f"training task (the paper: 50 x 3 seeds); success rate (%), mean over tasks ± s.e. over tasks.\n\n"
        + markdown_table(header, rows)
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "libero_cpu.md").write_text(text)
    if chart:
        bar_chart(chart, args.out / "libero_cpu.png", "success (%)", "LIBERO-Gen Combination, state-only, CPU scale")
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=["bpp", "goal_image", "language", "icrt"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    add_budget_arguments(parser)
    parser.add_argument("--rollouts", type=int, default=10, help="rollouts per held-out task")
    parser.add_argument("--train-tasks", type=int, default=10, help="training tasks evaluated (spread evenly)")
    parser.add_argument("--train-rollouts", type=int, default=4, help="rollouts per training task evaluated")
    parser.add_argument("--lane", type=int, default=0)
    parser.add_argument("--lanes", type=int, default=1)
    parser.add_argument("--workers", type=int, default=0, help="generation processes (0: one per core)")
    parser.add_argument("--data-preset", choices=sorted(PRESETS), default="cpu", help="training data (debug: a trial)")
    parser.add_argument("--data-dir", type=Path, default=Path("data/libero"))
    parser.add_argument("--runs", type=Path, default=Path("runs/libero_cpu"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/libero_cpu"))
    parser.add_argument("--prepare-only", action="store_true")
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args()
    args.method_steps, args.method_batch = budgets(args)
    if args.report_only:
        print(report(args))
        return
    if args.prepare_only:
        training_store(args)
        BENCHMARK.task_set("held-out", args.data_dir)
        return
    jobs = [(m, s) for s in args.seeds for m in args.methods][args.lane :: args.lanes]
    for method, seed in jobs:
        print(f"[libero_cpu] lane {args.lane}: {method} seed {seed}", flush=True)
        run_method(method, seed, args)
    print(report(args))


if __name__ == "__main__":
    main()
