"""The paper's six DrawAnything ablations at CPU scale, as one figure and one table.

    OMP_NUM_THREADS=1 python bench/draw_ablations.py --prepare-only          # generate every store once
    OMP_NUM_THREADS=1 python bench/draw_ablations.py --lane 0 --lanes 2 &    # two one-thread lanes on 2 cores
    OMP_NUM_THREADS=1 python bench/draw_ablations.py --lane 1 --lanes 2 &
    python bench/draw_ablations.py --report-only --figure docs/figures/draw_ablations.png   # figure + table

Panels (the paper's Fig. "BPP ablations on DrawAnything-Sim"); every arm is BPP with the main table's size and
observation preset (`cpu`, `board`: state-only, board-frame actions) and changes one thing against the shared
baseline (500 procedural tasks x 5 demos of 1-6 parts, Δt = 10, attention pooling, full prompt):

    a  prompt content: without state (obs + proprio; in this state-only preset the prompt's observation *is* the
       proprioception: cursor, pen, ink length), without actions
    b  prompt observation frequency: Δt = 2, 5, 10 (baseline, 1 Hz), 20 (0.5 Hz)
    c  attention pooling of each chunk into one token (baseline) vs one token per modality
    d  a fixed budget of 2500 demonstrations: 500x5 (baseline), 250x10, 100x25
    e  more training tasks at 5 demos each: 100, 250, 500 (baseline), 1000
    f  training drawing complexity: 1-3 parts, 4-6 parts, 1-6 parts (baseline), each 500x5; also evaluated on
       unseen procedural drawings of each complexity (20 tasks each, seed 1)

Every arm trains the same number of steps (--steps) with the same seed(s) and batch, and is evaluated with the
paper's protocol on the 50 unseen human-made drawings (--rollouts per drawing). Nothing is tuned on the evaluation
drawings. For each arm the report gives the paired difference against the baseline over the 50 drawings and its
standard error, and whether it points the paper's way, the opposite way, or shows no measurable effect (|diff| <
2 s.e.). Re-running reuses finished stores, runs and evaluations and resumes killed training.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import PRESETS as DATA_PRESETS
from bpp.benchmarks.draw.dataset import DrawDataConfig, generate
from bpp.checkpoint import Checkpoint
from bpp.data.store import EpisodeStore, stored_or_made
from bpp.drawing.procedural import ProceduralConfig
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import markdown_table
from bpp.policies.registry import get_method
from bpp.utils import write_json_atomic
from common import paired, sem, task_means, train_run

PARTS = {"1-3": ProceduralConfig(min_parts=1, max_parts=3), "4-6": ProceduralConfig(min_parts=4, max_parts=6)}


@dataclass(frozen=True)
class Arm:
    """One configuration: a training store and prompt settings; `key` names its store-independent run folder."""

    key: str
    label: str
    tasks: int = 500
    demos: int = 5
    parts: str = "1-6"
    prompt: dict = field(default_factory=dict)
    """Overrides of BPP's PromptConfig."""

    def data(self, scale: float = 1.0) -> DrawDataConfig:
        """The training data; `scale` shrinks the task count (a quick trial of the whole pipeline)."""
        procedural = PARTS.get(self.parts, ProceduralConfig())
        tasks = max(2, round(self.tasks * scale))
        return DrawDataConfig(num_tasks=tasks, demos_per_task=self.demos, procedural=procedural)

    def store_name(self, scale: float = 1.0) -> str:
        if (self.tasks, self.demos, self.parts, scale) == (500, 5, "1-6", 1.0):
            return "train-500.zarr"  # the main job's store (the `cpu` data preset)
        return f"abl-{self.data(scale).num_tasks}x{self.demos}-parts{self.parts}.zarr"


BASE = Arm("base", "baseline")
PANELS: dict[str, tuple[str, str, list[Arm]]] = {
    # panel: (title, the paper's finding, arms in display order; BASE is drawn where it belongs in the series)
    "a": (
        "prompt content",
        "removing observations or actions hurts; proprio does not matter",
        [
            BASE,
            Arm("no-state", "no obs/proprio", prompt={"use_obs": False, "use_proprio": False}),
            Arm("no-action", "no actions", prompt={"use_action": False}),
        ],
    ),
    "b": (
        "prompt frequency (Δt)",
        "under 1 Hz (Δt > 10) hurts",
        [
            Arm("dt2", "Δt 2 (5 Hz)", prompt={"chunk_len": 2}),
            Arm("dt5", "Δt 5 (2 Hz)", prompt={"chunk_len": 5}),
            replace(BASE, label="Δt 10 (1 Hz)"),
            Arm("dt20", "Δt 20 (0.5 Hz)", prompt={"chunk_len": 20}),
        ],
    ),
    "c": (
        "pooling",
        "attention pooling beats one token per modality",
        [replace(BASE, label="pooled"), Arm("pool-none", "per modality", prompt={"pooling": "none"})],
    ),
    "d": (
        "fixed budget, 2500 demos",
        "more tasks with fewer demos each is better",
        [
            replace(BASE, label="500x5"),
            Arm("250x10", "250x10", tasks=250, demos=10),
            Arm("100x25", "100x25", tasks=100, demos=25),
        ],
    ),
    "e": (
        "training tasks (5 demos each)",
        "more tasks is better",
        [
            Arm("100x5", "100", tasks=100),
            Arm("250x5", "250", tasks=250),
            replace(BASE, label="500"),
            Arm("1000x5", "1000", tasks=1000),
        ],
    ),
    "f": (
        "training drawing complexity",
        "1-3 parts is worst on unseen drawings, 4-6 best",
        [
            Arm("parts1-3", "1-3 parts", parts="1-3"),
            Arm("parts4-6", "4-6 parts", parts="4-6"),
            replace(BASE, label="1-6 parts"),
        ],
    ),
}
PAPER_SIGN = {
    "no-state": +1,
    "no-action": +1,
    "dt20": +1,
    "pool-none": +1,
    "250x10": +1,
    "100x25": +1,
    "100x5": +1,
    "250x5": +1,
    "1000x5": -1,
    "parts1-3": +1,
    "parts4-6": -1,
}
"""The sign of (arm - baseline) Chamfer the paper's figure shows (+1: the arm is worse); arms without an entry
(Δt 2 and 5) are not expected to differ."""
VAL_SETS = {"1-3": "val-parts1-3-seed1.zarr", "4-6": "val-parts4-6-seed1.zarr", "1-6": "val-seed1.zarr"}


def arms() -> list[Arm]:
    """Every distinct arm once, the baseline first."""
    unique: dict[str, Arm] = {}
    for _, _, panel_arms in PANELS.values():
        for arm in panel_arms:
            unique.setdefault(arm.key, replace(arm, label=BASE.label) if arm.key == "base" else arm)
    return [unique.pop("base"), *unique.values()]


def store_for(path: Path, cfg: DrawDataConfig) -> EpisodeStore:
    """The store at `path` if it holds exactly `cfg`'s data, else generated anew."""

    def make(path: Path) -> EpisodeStore:
        if path.exists():
            print(f"[ablations] {path} holds other data than this arm's; generating it again")
        return generate(cfg, path, overwrite=True)

    return stored_or_made(path, make, cfg)


def val_config(parts: str) -> DrawDataConfig:
    return DrawDataConfig(num_tasks=20, seed=1, procedural=PARTS.get(parts, ProceduralConfig()))


def per_drawing(path: Path) -> dict[str, float] | None:
    """Task id -> score_mean of an evaluation's results.json (None if it has not run)."""
    if not path.is_file():
        return None
    return task_means(json.loads(path.read_text()))


def run_arm(arm: Arm, seed: int, args) -> None:
    store = store_for(args.data_dir / arm.store_name(args.data_scale), arm.data(args.data_scale))
    base_cfg = get_method("bpp").config("cpu", "board", BENCHMARK)
    model_cfg = replace(base_cfg, prompt=replace(base_cfg.prompt, **arm.prompt))
    run = args.runs / f"{arm.key}-s{seed}"
    seconds = train_run(
        "bpp", "cpu", "board", store, run, args.steps, seed, tasks_per_batch=8, threads=1, model_cfg=model_cfg
    )
    write_json_atomic(run / "arm.json", {"arm": arm.key, "train_s": seconds, "steps": args.steps})
    checkpoint = Checkpoint.load(run, use_ema=True)
    protocol = Protocol(rollouts=args.rollouts)
    sets = {"human": "human"}
    if arm.key in ("base", "parts1-3", "parts4-6"):
        for parts, name in VAL_SETS.items():
            sets[f"val-{parts}"] = str(store_for(args.data_dir / name, val_config(parts)).path)
    for name, tasks in sets.items():
        _, task_set, indices = resolve_tasks(tasks, checkpoint, data_dir=args.data_dir, num_tasks=args.eval_tasks)
        evaluate(checkpoint, task_set, indices, args.out / f"{arm.key}-s{seed}" / name, protocol, workers=1, videos=0)


def report(args) -> str:
    """The table (Markdown) and the six-panel figure from whatever has been evaluated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def scores(arm: Arm, name: str = "human") -> dict[str, float] | None:
        seeds = [per_drawing(args.out / f"{arm.key}-s{s}" / name / "results.json") for s in args.seeds]
        seeds = [s for s in seeds if s]
        if not seeds:
            return None
        return {t: float(np.mean([s[t] for s in seeds])) for t in seeds[0]}

    def train_minutes(arm: Arm) -> str:
        values = []
        for s in args.seeds:
            info = args.runs / f"{arm.key}-s{s}" / "arm.json"
            if info.is_file():
                values.append(json.loads(info.read_text())["train_s"] / 60)
        return f"{np.mean(values):.0f}" if values else "-"

    base = scores(BASE)
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    drawings = len(base) if base else 0
    lines = [
        f"Unseen human-made drawings, Chamfer (px, lower is better), mean over the {drawings} drawings ± s.e.m.; "
        f"BPP `cpu` + `board`, {args.steps} steps, batch 64 with 8 prompts per step, seeds {args.seeds}, "
        f"{args.rollouts} rollouts per drawing.",
        "",
    ]
    rows = []
    for ax, (panel, (title, finding, panel_arms)) in zip(axes.flat, PANELS.items(), strict=True):
        labels, means, errs, colours = [], [], [], []
        for arm in panel_arms:
            values = scores(arm)
            labels.append(arm.label)
            colours.append("#c44e52" if arm.key == "base" else "#4c72b0")
            if values is None:
                means.append(np.nan)
                errs.append(0.0)
                rows.append((panel, arm.label, "not run yet", "", "", train_minutes(arm)))
                continue
            x = np.array(list(values.values()))
            means.append(x.mean())
            errs.append(sem(x))
            if arm.key == "base" or base is None:
                rows.append(
                    (panel, arm.label, f"{x.mean():.2f} ± {errs[-1]:.2f}", "(baseline)", "", train_minutes(arm))
                )
                continue
            diff = paired(base, values)
            expected = PAPER_SIGN.get(arm.key, 0)
            if abs(diff.diff) < 2 * diff.sem:
                verdict = "no measurable effect" + (" (paper: none either)" if expected == 0 else "")
            elif expected == 0:
                verdict = "an effect the paper does not show"
            else:
                verdict = "same way as the paper" if np.sign(diff.diff) == expected else "opposite to the paper"
            rows.append((panel, arm.label, f"{x.mean():.2f} ± {errs[-1]:.2f}", str(diff), verdict, train_minutes(arm)))
        bars = ax.bar(range(len(labels)), means, yerr=errs, capsize=3, color=colours)
        ax.bar_label(bars, fmt="%.1f", fontsize=7, padding=2)
        ax.set_xticks(range(len(labels)), labels, fontsize=8, rotation=15)
        ax.set_title(f"({panel}) {title}\npaper: {finding}", fontsize=9)
        ax.set_ylim(0, np.nanmax([m + e for m, e in zip(means, errs, strict=True)] + [1.0]) * 1.15)
        ax.set_ylabel("Chamfer (px)", fontsize=8)
    fig.suptitle(
        "BPP ablations on DrawAnything-Sim at CPU scale (unseen drawings; red: the shared baseline)", fontsize=11
    )
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    for path in (args.out / "ablations.png", *([args.figure] if args.figure else [])):
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    plt.close(fig)
    header = ["panel", "arm", "Chamfer (px)", "minus baseline (paired, ± s.e.)", "vs the paper", "train min"]
    lines.append(markdown_table(header, rows))
    complexity = []
    for arm in PANELS["f"][2]:
        row = [arm.label]
        for name in [*(f"val-{parts}" for parts in VAL_SETS), "human"]:
            values, reference = scores(arm, name), scores(BASE, name)
            if not values:
                row.append("-")
                continue
            cell = f"{np.mean(list(values.values())):.2f}"
            if arm.key != "base" and reference:
                cell += f" ({paired(reference, values)})"
            row.append(cell)
        complexity.append(tuple(row))
    lines += [
        "",
        "Panel (f) on unseen procedural drawings of each complexity (20 tasks each, seed 1) and on the human ones; "
        "in brackets, the paired difference from the 1-6-part baseline ± s.e. (compare within a column: drawings of "
        "different complexity have different Chamfer scales):",
        "",
        markdown_table(["trained on", "1-3 parts", "4-6 parts", "1-6 parts", "human"], complexity),
    ]
    text = "\n".join(lines) + "\n"
    (args.out / "ablations.md").write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=4000, help="training steps of every arm")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--rollouts", type=int, default=8, help="rollouts per unseen drawing")
    parser.add_argument("--lane", type=int, default=0, help="run the arms i with i %% lanes == lane")
    parser.add_argument("--lanes", type=int, default=1)
    parser.add_argument("--prepare-only", action="store_true", help="generate every store, train nothing")
    parser.add_argument("--report-only", action="store_true", help="write the figure and table from stored results")
    parser.add_argument("--eval-tasks", type=int, default=0, help="drawings per evaluation (0: all; a quick trial)")
    parser.add_argument("--data-scale", type=float, default=1.0, help="shrink every task count (a quick trial)")
    parser.add_argument("--data-dir", type=Path, default=Path("data/draw"))
    parser.add_argument("--runs", type=Path, default=Path("runs/ablations"))
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/ablations"))
    parser.add_argument("--figure", type=Path, default=None, help="also write the figure here (e.g. docs/figures/)")
    args = parser.parse_args()
    if not 0 <= args.lane < args.lanes:
        parser.error(f"--lane must be in [0, --lanes), got {args.lane} of {args.lanes}")
    if not args.report_only:
        if args.prepare_only:
            store_for(args.data_dir / "human.zarr", DATA_PRESETS["human"])
            for parts, name in VAL_SETS.items():
                store_for(args.data_dir / name, val_config(parts))
            for arm in arms():
                store_for(args.data_dir / arm.store_name(args.data_scale), arm.data(args.data_scale))
            return
        jobs = [(arm, seed) for seed in args.seeds for arm in arms()]
        for i, (arm, seed) in enumerate(jobs):
            if i % args.lanes == args.lane:
                print(f"[ablations] lane {args.lane}: {arm.key} seed {seed}")
                run_arm(arm, seed, args)
    print(report(args))


if __name__ == "__main__":
    main()
