"""The DrawAnything-Sim result on a CPU: BPP against its baselines with the same data, budget and seeds.

    python bench/draw_cpu_benchmark.py                                  # defaults below; ~1.5 h on 2 cores
    python bench/draw_cpu_benchmark.py --methods bpp icrt --seeds 0 1 2 --steps bpp=6000 icrt=4000
    python bench/draw_cpu_benchmark.py --seeds 0 1 2 --report-only    # table of whatever has finished training
    python bench/draw_cpu_benchmark.py --methods bpp --obs image64 --out outputs/bench/draw_cpu_image  # a camera

Every method trains the same size preset (`--preset`, default `cpu`) observing the same DrawAnything observation
preset (`--obs`, default `board`: state and actions in the board's frame, not the paper's setting). Runs are named
`{method}-{preset}-{obs}-s{seed}`, except that a pair with a name from before presets were split into sizes and
observations keeps it (`cpu` + `board` is `cpu-board`, `cpu` + `image64` is `cpu-image`), so earlier runs are found.

Generates the data (procedural training tasks, the unseen human-made drawings), trains every method x seed on the
same training store (skipping runs that already finished, resuming killed ones), evaluates each with the paper's
protocol on the unseen drawings and on training drawings, and writes a Markdown table, a JSON file and a bar chart
into --out. Training wall time is measured and reported per run. Re-running reuses everything already done, so
several invocations can train different methods or seeds side by side (one core each), and a last `--report-only`
call gathers them into one table. Each run's scores are kept in `--out/<run>/entry.json`: the table is made of those,
so a run whose checkpoint was deleted to free the disk still counts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import PRESETS as DATA_PRESETS
from bpp.benchmarks.draw.dataset import DrawDataConfig, generate
from bpp.checkpoint import Checkpoint
from bpp.data.store import EpisodeStore, stored_or_made
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import bar_chart, markdown_table
from bpp.policies.registry import get_method
from bpp.utils import write_json_atomic
from common import NAMES, add_budget_arguments, budgets, paired, train_run, trained_to


def store_for(path: Path, cfg: DrawDataConfig) -> EpisodeStore:
    """The store at `path` (whatever it holds), else `cfg`'s data generated there."""
    return stored_or_made(path, lambda path: generate(cfg, path, overwrite=True))


def _sd(x: np.ndarray) -> float:
    """Standard deviation over seeds (0 for a single seed)."""
    return float(x.std(ddof=1)) if len(x) > 1 else 0.0


def _mean_sd(x: np.ndarray) -> str:
    """'mean ± std over seeds', or the bare value of a single seed (it has no spread to show)."""
    return f"{x.mean():.2f} ± {_sd(x):.2f}" if len(x) > 1 else f"{x.mean():.2f}"


def _seed_averaged(per_seed: list[dict[str, float]]) -> dict[str, float]:
    """Each drawing's task mean, averaged over seeds (every seed evaluates the same drawings)."""
    return {task: float(np.mean([seed[task] for seed in per_seed])) for task in per_seed[0]}


ENTRY = "entry.json"
"""A run's scores, training time and budget, in its folder of --out."""


def _kept_entry(folder: Path, wanted: dict) -> dict | None:
    """The run's kept scores if they are of this budget and evaluation (`wanted`: the fields that must match)."""
    path = folder / ENTRY
    if not path.is_file():
        return None
    entry = json.loads(path.read_text())
    return entry if all(entry.get(key) == value for key, value in wanted.items()) else None


def _paired(a: str, b: str, drawings: dict[str, dict[str, float]]) -> str:
    """`a` minus `b` paired over the drawings both evaluated: the mean difference, its standard error and the count
    of drawings where `a` is better (lower)."""
    result = paired(drawings[b], drawings[a])
    return (
        f"{a} minus {b}, paired over the {result.tasks} unseen drawings (each averaged over seeds): "
        f"{result} px (s.e.m.); {a} is better on {result.b_better} of them"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", nargs="+", default=["bpp", "goal_image", "icrt"])
    parser.add_argument("--preset", default="cpu", help="model size preset, the same for every method")
    parser.add_argument("--obs", default="board", help="DrawAnything observation preset, the same for every method")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    add_budget_arguments(parser)
    parser.add_argument("--tasks-per-batch", type=int, default=8, help="tasks (prompts) per step, all methods")
    parser.add_argument(
        "--threads", type=int, default=0, help="torch threads for training (0: TrainConfig's auto, the cores minus one)"
    )
    parser.add_argument("--num-tasks", type=int, default=500, help="procedural training tasks (5 demos each)")
    parser.add_argument("--rollouts", type=int, default=8, help="rollouts per unseen drawing (paper: 32)")
    parser.add_argument("--train-tasks", type=int, default=20, help="training drawings evaluated")
    parser.add_argument("--human-tasks", type=int, default=0, help="unseen human drawings evaluated (0: all 50)")
    parser.add_argument(
        "--loader-workers", type=int, default=0, help="data-loader processes per training run (a GPU: several)"
    )
    parser.add_argument("--compile", default="off", help="`bpp train --compile` mode of every training run")
    parser.add_argument(
        "--frames-on", default="loader", choices=["loader", "device"], help="`bpp train --frames-on` of every run"
    )
    parser.add_argument("--data-dir", type=Path, default=Path("data/draw"))
    parser.add_argument("--runs", type=Path, default=Path("runs/bench"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/draw_cpu"))
    parser.add_argument("--workers", type=int, default=0, help="evaluation processes (0: one per core)")
    parser.add_argument(
        "--n-action-steps",
        type=int,
        default=0,
        help="actions executed per inference by the methods with a diffusion decoder (0: their Ta); ICRT's "
        "context is built one whole chunk at a time, so it always executes its chunk",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: evaluate and tabulate the runs that have finished training, skip the others",
    )
    parser.add_argument(
        "--train-only",
        action="store_true",
        help="train (or finish) the runs and evaluate nothing: a later --report-only call evaluates them, e.g. once "
        "several training processes that shared the machine are done",
    )
    args = parser.parse_args()
    if args.train_only and args.report_only:
        parser.error("--train-only and --report-only exclude each other")
    steps, batch = budgets(args)
    label = f"{args.preset}-{args.obs}"

    train_store = store_for(args.data_dir / f"train-{args.num_tasks}.zarr", DrawDataConfig(num_tasks=args.num_tasks))
    store_for(args.data_dir / "human.zarr", DATA_PRESETS["human"])
    rows, results = [], {}
    for method in args.methods:
        model_cfg = get_method(method).config(args.preset, args.obs, BENCHMARK)  # refuses unknown presets early
        replans = hasattr(model_cfg, "diffusion")  # ICRT executes whole chunks
        protocol = Protocol(rollouts=args.rollouts, n_action_steps=args.n_action_steps if replans else 0)
        for seed in args.seeds:
            run = args.runs / f"{method}-{label}-s{seed}"
            wanted = {"run": str(run), "steps": steps[method], "batch_size": batch[method]}
            wanted |= {"n_action_steps": protocol.n_action_steps, "rollouts": args.rollouts}
            wanted |= {"human_tasks": args.human_tasks, "train_tasks": args.train_tasks}
            kept = _kept_entry(args.out / run.name, wanted)
            if kept is not None and not args.train_only:
                results[f"{method}/s{seed}"] = kept
                continue
            if args.report_only and not (trained_to(run, steps[method]) and (run / "train_seconds.json").is_file()):
                print(f"skipping {run}: not trained to {steps[method]} steps")
                continue
            seconds = train_run(
                method,
                args.preset,
                args.obs,
                train_store,
                run,
                steps[method],
                seed,
                batch[method],
                args.tasks_per_batch,
                args.threads,
                loader_workers=args.loader_workers,
                compile=args.compile,
                frames_on=args.frames_on,
            )
            if args.train_only:
                print(f"trained {run} ({seconds / 60:.1f} min of training)")
                continue
            entry = {"method": method, "seed": seed, **wanted, "train_s": seconds}  # what a later call matches on
            checkpoint = Checkpoint.load(run, use_ema=True)
            for name, num in (("human", args.human_tasks), ("train", args.train_tasks)):
                _, task_set, tasks = resolve_tasks(name, checkpoint, data_dir=args.data_dir, num_tasks=num)
                out = args.out / run.name / name
                data = evaluate(checkpoint, task_set, tasks, out, protocol, args.workers)
                entry[name] = data["summary"]["score_mean"]  # the best Chamfer distance, px
                entry[f"{name}_median_rollout"] = data["summary"]["score_median_rollout"]
                entry[f"{name}_per_task"] = {str(t["task"]): t["score_mean"] for t in data["tasks"]}  # as JSON keeps it
            results[f"{method}/s{seed}"] = entry
            write_json_atomic(args.out / run.name / ENTRY, entry)
    if args.train_only:
        return  # nothing evaluated: a later --report-only call tabulates
    write_json_atomic(args.out / "results.json", results)

    chart: dict[str, dict[str, tuple[float, float]]] = {"unseen human drawings": {}, "training drawings": {}}
    drawings: dict[str, dict[str, float]] = {}  # method name -> unseen drawing -> Chamfer averaged over seeds
    for method in args.methods:
        entries = [e for e in results.values() if e["method"] == method]
        if not entries:
            continue
        human = np.array([e["human"] for e in entries])
        trained = np.array([e["train"] for e in entries])
        chart["unseen human drawings"][NAMES[method]] = (float(human.mean()), _sd(human))
        chart["training drawings"][NAMES[method]] = (float(trained.mean()), _sd(trained))
        minutes = np.mean([e["train_s"] for e in entries]) / 60
        medians = np.mean([e["human_median_rollout"] for e in entries])
        drawings[NAMES[method]] = _seed_averaged([e["human_per_task"] for e in entries])
        rows.append(
            (
                NAMES[method],
                _mean_sd(trained),
                _mean_sd(human),
                f"{medians:.2f}",
                len(entries),
                f"{steps[method]} x {batch[method]}",
                f"{minutes:.1f}",
            )
        )
    if args.train_only:
        return
    if not rows:  # e.g. --report-only before anything finished training: the data is there, nothing to tabulate
        print("no run has finished training yet: nothing to tabulate")
        return
    header = [
        "method",
        "training drawings (px)",
        "unseen human drawings (px)",
        "median unseen rollout",
        "seeds",
        "steps x batch",
        "train min",
    ]
    table = markdown_table(header, rows)
    unseen = chart["unseen human drawings"]  # {name: (mean, std)}
    findings = [
        f"BPP / {name} on the unseen drawings: {unseen['BPP'][0] / unseen[name][0]:.3f} (target at most {target})"
        for name, target in (("Goal-Image", 0.3), ("ICRT", 0.75))
        if "BPP" in unseen and name in unseen
    ]
    findings += [_paired("BPP", name, drawings) for name in ("Goal-Image", "ICRT") if {"BPP", name} <= drawings.keys()]
    for method in args.methods:
        seeds = sorted((e["seed"], e["human"]) for e in results.values() if e["method"] == method)
        if len(seeds) > 1:
            findings.append(
                f"{NAMES[method]} on the unseen drawings by seed: " + ", ".join(f"s{k} {v:.2f}" for k, v in seeds)
            )
    if findings:
        table += "\n" + "\n".join(f"- {line}" for line in findings) + "\n"
    executed = ""
    if args.n_action_steps:
        executed = f" The diffusion-decoder methods execute {args.n_action_steps} actions per inference."
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table.md").write_text(
        f"DrawAnything-Sim, preset `{label}`, {args.num_tasks} tasks x 5 demos, "
        f"{args.rollouts} rollouts per unseen drawing, {args.train_tasks} training drawings; Chamfer px at 512, "
        f"mean ± std over seeds.{executed}\n\n{table}"
    )
    bar_chart(chart, args.out / "chart.png", "Chamfer distance (px, lower is better)", f"DrawAnything-Sim, {label}")
    print(table)
    print(f"wrote {args.out / 'table.md'}, {args.out / 'chart.png'}, {args.out / 'results.json'}")


if __name__ == "__main__":
    main()
