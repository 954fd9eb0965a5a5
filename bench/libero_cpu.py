"""LIBERO-Gen at CPU scale: BPP against Goal-Image, Language and ICRT on a suite's 10 held-out tasks, with the same
data, observation preset (`state`: proprioception + object poses, not the paper's cameras), budget and seeds.

    python bench/libero_cpu.py --prepare-only                   # the training store and the held-out tasks, once
    OMP_NUM_THREADS=1 python bench/libero_cpu.py --lane 0 --lanes 2 &     # two one-thread lanes on the 2 cores
    OMP_NUM_THREADS=1 python bench/libero_cpu.py --lane 1 --lanes 2 &
    python bench/libero_cpu.py --report-only                    # table + chart from whatever has been evaluated
    python bench/libero_cpu.py --suite chain ...                # the same for Chain

Data (Combination): the `cpu` data preset (every training task x 3 scripted demonstrations, state only; about an
hour to generate on 2 cores) and the `held-out` task set (the 10 held-out tasks x 5 demonstrations, the prompts);
for Chain, `chain-cpu` (311 tasks x 2) and `chain-held-out`. Each method trains `--steps` steps of its `cpu` size
preset with one thread, then is evaluated with the paper's protocol (success by LIBERO's predicates, each rollout
from its own initial state, at most 550 steps) on the held-out tasks and on --train-tasks training tasks. Chain's
scripted demonstrations take up to about 1000 steps for two steps, so its rollouts run to --max-steps (default
1100) and the report gives success within 550 steps (the paper's limit) and within --max-steps. Re-running reuses
finished stores, runs and evaluations and resumes killed training.

One scene instead (the ladder's rungs b and c): a store of its training tasks, its held-out tasks as a store of
prompts, position goals, and the same initial states for every seed:

    OMP_NUM_THREADS=1 python bench/libero_cpu.py --train-store data/libero/s9-train-50.zarr \
        --held-out data/libero/s9-test-10.zarr --obs state-abs --eval-seed 0 --rollouts 50 --train-tasks 15 \
        --train-rollouts 10 --steps bpp=12000 goal_image=12000 language=12000 icrt=2600 --seeds 0 1 2 \
        --runs runs/libero/s9 --out outputs/bench/libero_s9 --lane 0 --lanes 2 &    # and --lane 1
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.benchmark import BENCHMARK
from bpp.benchmarks.libero.dataset import PRESETS, generate
from bpp.checkpoint import Checkpoint
from bpp.data.store import EpisodeStore, stored_with
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import bar_chart, markdown_table
from bpp.policies.registry import get_method
from bpp.utils import write_json_atomic
from common import NAMES, add_budget_arguments, budgets, train_run

PAPER = {
    "combination": {"goal_image": (59.1, 47.9), "language": (80.0, 69.9), "bpp": (88.4, 79.1)},
    "chain": {"goal_image": (77.8, 58.5), "language": (87.2, 80.3), "bpp": (85.5, 88.9)},
}
"""The paper's success rates (%), training tasks / unseen tasks (cameras, GPUs, 3 seeds)."""
SUITES = {  # data preset, held-out task set, default rollout limit
    "combination": ("cpu", "held-out", 550),
    "chain": ("chain-cpu", "chain-held-out", 1100),
}
PAPER_LIMIT = 550
"""The authors' rollout limit (ANCHORS.md)."""


def training_store(args):
    """--train-store, else the training store of --data-preset (`cpu`: the one `bpp libero generate --preset cpu`
    writes by default), generated on first use."""
    if args.train_store:
        return EpisodeStore(args.train_store)
    default = SUITES[args.suite][0]
    name = f"{args.suite}-train" + ("" if args.data_preset == default else f"-{args.data_preset}")
    path = args.data_dir / f"{name}.zarr"
    store = stored_with(path, PRESETS[args.data_preset])
    if store is None:
        store = generate(PRESETS[args.data_preset], path, workers=args.workers, overwrite=path.exists())
    return store


def long_prompts(model_cfg, longest: int, rollout: int):
    """Room for prompts of `longest` steps (Chain's demonstrations are up to 1200 steps long, more than the `cpu`
    presets' 800): BPP takes them whole, and ICRT's context (two tokens per chunk) holds one and a `rollout`-step
    rollout."""
    if hasattr(model_cfg, "prompt") and longest > model_cfg.prompt.max_steps:  # BPP
        return replace(model_cfg, prompt=replace(model_cfg.prompt, max_steps=longest))
    if hasattr(model_cfg, "max_tokens"):  # ICRT
        chunks = -(-longest // model_cfg.chunk_len) + -(-rollout // model_cfg.chunk_len)
        return replace(model_cfg, max_tokens=max(model_cfg.max_tokens, 2 * chunks + 16))
    return model_cfg


def run_method(method: str, seed: int, args) -> None:
    store = training_store(args)
    run = args.runs / f"{method}-s{seed}"
    longest = PRESETS[args.data_preset].demo.max_steps
    model_cfg = long_prompts(get_method(method).config("cpu", args.obs, BENCHMARK), longest, args.max_steps)
    steps, batch = args.method_steps[method], args.method_batch[method]
    seconds = train_run(method, "cpu", args.obs, store, run, steps, seed, batch_size=batch, tasks_per_batch=8,
                        threads=1, model_cfg=model_cfg)  # fmt: skip
    write_json_atomic(run / "train.json", {"train_s": seconds, "steps": steps, "batch": batch})
    checkpoint = Checkpoint.load(run, use_ema=True)
    eval_seed = seed if args.eval_seed < 0 else args.eval_seed
    for name, tasks, count, rollouts in (
        ("held-out", args.held_out or SUITES[args.suite][1], 0, args.rollouts),
        ("train", "train", args.train_tasks, args.train_rollouts),
    ):
        protocol = Protocol(rollouts=rollouts, seed=eval_seed, max_steps=args.max_steps)
        _, task_set, indices = resolve_tasks(tasks, checkpoint, data_dir=args.data_dir, num_tasks=count)
        evaluate(checkpoint, task_set, indices, args.out / f"{method}-s{seed}" / name, protocol, workers=1, videos=2)


def _partial(out: Path, method: str, seeds, keys=("lifted", "lifted_other")) -> str:
    """How often held-out rollouts reached a partial record (% of rollouts, joined by " / "): lifting the object
    their goal moves, any other object, or (Chain) the first step's goal; a dash where none recorded it."""
    rows = []
    for seed in seeds:
        path = out / f"{method}-s{seed}" / "held-out" / "results.json"
        if path.is_file():
            rows += json.loads(path.read_text())["rollouts"]
    if not rows or any(key not in rows[0] for key in keys):
        return "-"
    return " / ".join(f"{100 * np.mean([r[key] for r in rows]):.0f}" for key in keys)


def per_task(path: Path, limit: int) -> dict[str, float] | None:
    """Task id -> success rate of an evaluation's rollouts that succeeded within `limit` steps (None if not run)."""
    if not path.is_file():
        return None
    rollouts = json.loads(path.read_text())["rollouts"]
    tasks = {r["task_id"]: [] for r in rollouts}
    for r in rollouts:
        tasks[r["task_id"]].append(r["score"] > 0 and r["steps"] <= limit)
    return {task: float(np.mean(done)) for task, done in tasks.items()}


def report(args) -> str:
    limits = sorted({min(PAPER_LIMIT, args.max_steps), args.max_steps})
    rows, chart = [], {}
    for method in args.methods:
        cells = []
        for split in ("train", "held-out"):
            texts = []
            for limit in limits:
                seeds = [per_task(args.out / f"{method}-s{s}" / split / "results.json", limit) for s in args.seeds]
                seeds = [s for s in seeds if s]
                if not seeds:
                    break
                x = 100 * np.array([np.mean(list(s.values())) for s in seeds])
                tasks = 100 * np.array([np.mean([s[t] for s in seeds]) for t in seeds[0]])
                se = tasks.std(ddof=1) / np.sqrt(len(tasks)) if len(tasks) > 1 else 0.0
                texts.append(f"{x.mean():.1f} ± {se:.1f}")
                if limit == limits[0]:
                    chart.setdefault(f"{split} tasks", {})[NAMES[method]] = (float(x.mean()), float(se))
            cells.append(f"{' / '.join(texts)} ({len(tasks)} tasks)" if texts else "not run yet")
        cells.append(_partial(args.out, method, args.seeds))
        if args.suite == "chain":
            cells.append(_partial(args.out, method, args.seeds, ("first_step",)))
        trained = [
            json.loads((args.runs / f"{method}-s{s}" / "train.json").read_text())
            for s in args.seeds
            if (args.runs / f"{method}-s{s}" / "train.json").is_file()
        ]
        minutes = [t["train_s"] / 60 for t in trained]
        budget = f"{trained[0]['steps']} x {trained[0].get('batch', 64)}" if trained else "-"
        paper = PAPER[args.suite].get(method)
        rows.append(
            (
                NAMES[method],
                *cells,
                f"{paper[0]} / {paper[1]}" if paper else "-",
                budget,
                f"{np.mean(minutes):.0f}" if minutes else "-",
            )
        )
    within = " / ".join(f"within {limit} steps" for limit in limits)
    header = ["method", f"training tasks (%, {within})", f"held-out tasks (%, {within})",
              "held-out: lifted the goal's object / another object (%)", "paper: train / unseen (%)", "steps x batch",
              "train min"]  # fmt: skip
    if args.suite == "chain":
        header.insert(4, "held-out: first step done (%)")
    suite = args.suite.capitalize()
    text = (
        f"LIBERO-Gen {suite}, `{args.obs}` observations (not the paper's cameras), `cpu` size presets trained with "
        f"one thread, seeds {args.seeds}, {args.rollouts} rollouts per held-out task and {args.train_rollouts} per "
        f"training task (the paper: 50 x 3 seeds, at most {PAPER_LIMIT} steps); success rate (%), mean over tasks ± "
        f"s.e. over tasks.\n\n" + markdown_table(header, rows)
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "libero_cpu.md").write_text(text)
    if chart:
        title = f"LIBERO-Gen {suite}, state-only, CPU scale (within {limits[0]} steps)"
        bar_chart(chart, args.out / "libero_cpu.png", "success (%)", title)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suite", choices=sorted(SUITES), default="combination")
    parser.add_argument("--methods", nargs="+", default=["bpp", "goal_image", "language", "icrt"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    add_budget_arguments(parser)
    parser.add_argument("--rollouts", type=int, default=10, help="rollouts per held-out task")
    parser.add_argument("--train-tasks", type=int, default=10, help="training tasks evaluated (spread evenly)")
    parser.add_argument("--train-rollouts", type=int, default=4, help="rollouts per training task evaluated")
    parser.add_argument("--lane", type=int, default=0)
    parser.add_argument("--lanes", type=int, default=1)
    parser.add_argument("--workers", type=int, default=0, help="generation processes (0: one per core)")
    parser.add_argument("--max-steps", type=int, default=0, help="rollout limit (0: the suite's, 550 or 1100)")
    parser.add_argument("--data-preset", choices=sorted(PRESETS), default="", help="training data (default: suite's)")
    parser.add_argument("--data-dir", type=Path, default=Path("data/libero"))
    parser.add_argument("--train-store", type=Path, help="a store to train on instead of --data-preset's")
    parser.add_argument("--held-out", default="", help="the held-out tasks: a named task set or a store path")
    parser.add_argument("--obs", default="state", help="the methods' observation preset (e.g. state-abs)")
    parser.add_argument("--eval-seed", type=int, default=-1, help="initial states' seed (-1: each run's seed)")
    parser.add_argument("--runs", type=Path, help="default: runs/libero_cpu (Chain: runs/libero_chain_cpu)")
    parser.add_argument("--out", type=Path, help="default: outputs/bench/libero_cpu (Chain: ..._chain_cpu)")
    parser.add_argument("--prepare-only", action="store_true")
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args()
    preset, task_set, limit = SUITES[args.suite]
    args.data_preset, args.max_steps = args.data_preset or preset, args.max_steps or limit
    folder = "libero_cpu" if args.suite == "combination" else f"libero_{args.suite}_cpu"
    args.runs, args.out = args.runs or Path("runs") / folder, args.out or Path("outputs/bench") / folder
    args.method_steps, args.method_batch = budgets(args)
    if args.report_only:
        print(report(args))
        return
    if args.prepare_only:
        training_store(args)
        if not args.held_out:
            BENCHMARK.task_set(task_set, args.data_dir)
        return
    jobs = [(m, s) for s in args.seeds for m in args.methods][args.lane :: args.lanes]
    for method, seed in jobs:
        print(f"[libero_cpu] lane {args.lane}: {method} seed {seed}", flush=True)
        run_method(method, seed, args)
    print(report(args))


if __name__ == "__main__":
    main()
