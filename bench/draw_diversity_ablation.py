"""Data diversity at a fixed demonstration budget: more tasks with fewer demos each, or fewer tasks with more.

    python bench/draw_diversity_ablation.py                      # 1000 demos as 200x5, 100x10, 50x20
    python bench/draw_diversity_ablation.py --budget 2500 --demos 5 10 25 --steps 4000

The paper's version: 10k demonstrations as 2000x5 / 1000x10 / 500x20. Every split trains BPP with the same size
preset (`--preset`, default `cpu`) observing the same DrawAnything observation preset (`--obs`, default `board`),
steps and seed, and is evaluated with the paper's protocol on the unseen human-made drawings and on a validation
split of unseen procedural tasks. Writes a table and a chart into --out; re-running reuses finished work.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bpp.benchmarks.draw.dataset import PRESETS as DATA_PRESETS
from bpp.benchmarks.draw.dataset import DrawDataConfig
from bpp.checkpoint import Checkpoint
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import bar_chart, markdown_table
from bpp.utils import write_json_atomic
from common import train_run
from draw_cpu_benchmark import preset_label, store_for


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budget", type=int, default=1000, help="demonstrations in every training set")
    parser.add_argument("--demos", nargs="+", type=int, default=[5, 10, 20], help="demos per task of each split")
    parser.add_argument("--preset", default="cpu", help="BPP's size preset")
    parser.add_argument("--obs", default="board", help="DrawAnything observation preset")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tasks-per-batch", type=int, default=8, help="tasks (prompts) per step, as the benchmark")
    parser.add_argument(
        "--threads", type=int, default=0, help="torch threads for training (0: TrainConfig's auto, the cores minus one)"
    )
    parser.add_argument("--rollouts", type=int, default=8)
    parser.add_argument("--val-tasks", type=int, default=20, help="unseen procedural tasks (seed 1) evaluated")
    parser.add_argument("--data-dir", type=Path, default=Path("data/draw"))
    parser.add_argument("--runs", type=Path, default=Path("runs/diversity"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/diversity"))
    parser.add_argument("--workers", type=int, default=0)
    args = parser.parse_args()

    store_for(args.data_dir / "human.zarr", DATA_PRESETS["human"])
    val_path = args.data_dir / "val-seed1.zarr"
    store_for(val_path, DrawDataConfig(num_tasks=args.val_tasks, seed=1))
    protocol = Protocol(rollouts=args.rollouts)
    label = preset_label(args.preset, args.obs)  # e.g. cpu-board, as run folders were named before the split
    rows, chart, results = [], {"unseen human drawings": {}, "unseen procedural (val)": {}}, {}
    for demos in args.demos:
        tasks = args.budget // demos
        name = f"{tasks}x{demos}"
        cfg = DrawDataConfig(num_tasks=tasks, demos_per_task=demos, seed=args.seed)
        store = store_for(args.data_dir / f"diversity-{name}.zarr", cfg)
        run = args.runs / f"{name}-{label}-s{args.seed}"
        seconds = train_run(
            "bpp",
            args.preset,
            args.obs,
            store,
            run,
            args.steps,
            args.seed,
            tasks_per_batch=args.tasks_per_batch,
            threads=args.threads,
        )
        entry = {"tasks": tasks, "demos_per_task": demos, "run": str(run), "train_s": seconds}
        checkpoint = Checkpoint.load(run, use_ema=True)
        for key, task_set in (("human", "human"), ("val", str(val_path))):
            _, eval_set, eval_tasks = resolve_tasks(task_set, checkpoint, data_dir=args.data_dir)
            data = evaluate(checkpoint, eval_set, eval_tasks, args.out / name / key, protocol, args.workers)
            entry[key] = data["summary"]["score_mean"]  # the best Chamfer distance, px
        results[name] = entry
        write_json_atomic(args.out / "results.json", results)
        rows.append((name, tasks, demos, entry["val"], entry["human"], f"{seconds / 60:.1f}"))
        chart["unseen human drawings"][name] = (entry["human"], 0.0)
        chart["unseen procedural (val)"][name] = (entry["val"], 0.0)
    header = ["split", "tasks", "demos/task", "val Chamfer (px)", "human Chamfer (px)", "train min"]
    table = markdown_table(header, rows)
    (args.out / "table.md").write_text(
        f"BPP `{label}`, {args.budget} demonstrations per training set, {args.steps} steps of "
        f"{args.tasks_per_batch} tasks x 64 windows, seed {args.seed}, "
        f"{args.rollouts} rollouts per task.\n\n{table}"
    )
    bar_chart(chart, args.out / "chart.png", "Chamfer distance (px, lower is better)", f"{args.budget} demos")
    print(table)


if __name__ == "__main__":
    main()
