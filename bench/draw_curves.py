"""Learning curves on DrawAnything: every kept checkpoint of some training runs, scored on a procedural validation
split, against training minutes and training samples.

    bpp train --method bpp --out runs/curves/bpp-s0 --steps 32000 --save-every 4000 --keep-checkpoints 50 ...
    bpp train --method icrt --out runs/curves/icrt-s0 --steps 16000 --save-every 2000 --keep-checkpoints 50 ...
    python bench/draw_curves.py runs/curves/bpp-s0 runs/curves/icrt-s0 --at 4000 8000 16000 --human-final

The validation split is procedural drawings generated with another seed than the training store's (`--val`, made on
first use: 50 tasks x 5 demonstrations, seed 1), never the unseen human-made drawings, so a curve can choose a budget
or a setting without looking at the test set. `--human-final` also scores each run's last checkpoint on the 50 unseen
human-made drawings (the paper's protocol), once the choice is made.

A checkpoint's training minutes are its `state.json`'s modification time minus the run's `config.json`'s (written
when training starts): wall time, including any time the cores were shared. Each evaluation is kept under --out and
reused when the script runs again; the script writes results.json, table.md and curves.png there. Once checkpoints
are deleted, `--replot` draws the curves of several such results.json files (e.g. one per seed) in one figure:

    python bench/draw_curves.py --replot outputs/curves0/results.json outputs/curves1/results.json --out outputs/all
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from bpp.benchmarks.draw.dataset import DrawDataConfig
from bpp.checkpoint import Checkpoint, read_state, step_folders
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from bpp.evaluation.report import markdown_table
from bpp.media import pyplot, save_figure
from bpp.utils import read_json, write_json_atomic
from common import NAMES
from draw_cpu_benchmark import store_for

VAL = DrawDataConfig(num_tasks=50, demos_per_task=5, seed=1)
"""The validation split: procedural drawings of seed 1 (the training stores use seed 0)."""


def minutes_into(run: Path, ckpt: Path) -> float:
    """Wall minutes from the run's start (its config.json) to the checkpoint's write."""
    return ((ckpt / "state.json").stat().st_mtime - (run / "config.json").stat().st_mtime) / 60


def batch_size(run: Path) -> int:
    return int(json.loads((run / "config.json").read_text())["train_config"]["batch_size"])


def score(ckpt: Path, tasks: str, num: int, out: Path, rollouts: int, workers: int) -> dict:
    """The checkpoint's summary on `tasks` (a store path or a named set), evaluated once and kept in `out`."""
    kept = out / "summary.json"
    if kept.is_file():
        return json.loads(kept.read_text())
    checkpoint = Checkpoint.load(ckpt, use_ema=True)
    _, task_set, indices = resolve_tasks(tasks, checkpoint, num_tasks=num)
    summary = evaluate(checkpoint, task_set, indices, out, Protocol(rollouts=rollouts), workers)["summary"]
    write_json_atomic(kept, summary)
    return summary


MARKERS = "osD^v<>"
"""A run's marker among its method's runs (its colour is its method's)."""


def curve_name(method: str, run: Path) -> str:
    """A curve's name in results.json, the table and the legend: "BPP (bpp-s0)"."""
    return f"{NAMES.get(method, method)} ({run.name})"


def method_of(curve: str) -> str:
    """The method's display name in a :func:`curve_name` (saved curves keep no other record of it)."""
    return curve.split(" (")[0]


def plot(curves: dict[str, list[dict]], path: Path) -> None:
    fig, axes = pyplot().subplots(1, 2, figsize=(10, 4), sharey=True)
    colours: dict[str, str] = {}  # a method's colour, by the name before the run's
    runs_of: Counter[str] = Counter()  # runs of each method drawn so far
    for name, points in curves.items():
        method = method_of(name)
        colour = colours.setdefault(method, f"C{len(colours)}")
        marker = MARKERS[runs_of[method] % len(MARKERS)]
        runs_of[method] += 1
        for ax, key in zip(axes, ("minutes", "samples"), strict=True):
            x, y = [p[key] for p in points], [p["val"] for p in points]
            ax.plot(x, y, marker=marker, color=colour, alpha=0.85, label=name)
    axes[0].set_xlabel("training wall time (min)")
    axes[1].set_xlabel("training samples (windows or whole demonstrations)")
    axes[1].set_xscale("log")
    axes[0].set_ylabel("validation Chamfer (px, lower is better)")
    axes[0].legend()
    fig.suptitle("DrawAnything-Sim learning curves, procedural validation split")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def row(name: str, point: dict) -> tuple:
    return name, point["step"], f"{point['minutes']:.1f}", f"{point['val']:.2f}", f"{point['val_median']:.2f}"


def replot(files: list[Path]) -> tuple[dict[str, list[dict]], list[tuple]]:
    """The curves of saved results.json files, merged (a run named twice keeps its last file's curve)."""
    curves: dict[str, list[dict]] = {}
    for path in files:
        curves |= read_json(path, "curves file")
    curves = dict(sorted(curves.items()))  # a method's runs side by side
    return curves, [row(name, point) for name, points in curves.items() for point in points]


def score_runs(args) -> tuple[dict[str, list[dict]], list[tuple]]:
    """Every chosen checkpoint of `args.runs` scored on the validation split (and the last on human, if asked)."""
    store_for(args.val, VAL)
    curves: dict[str, list[dict]] = {}
    rows = []
    for run in args.runs:
        states = {c: read_state(c) for c in reversed(step_folders(run / "checkpoints"))}  # oldest first
        ckpts = [c for c, state in states.items() if not args.at or state["step"] in args.at]
        if not ckpts:
            print(f"skipping {run}: no complete checkpoint to score yet")
            continue
        method = states[ckpts[-1]]["method"]
        name = curve_name(method, run)
        points = []
        for ckpt in ckpts:
            summary = score(
                ckpt, str(args.val), args.num_tasks, args.out / run.name / ckpt.name, args.rollouts, args.workers
            )
            step = states[ckpt]["step"]
            point = {"step": step, "samples": step * batch_size(run), "minutes": minutes_into(run, ckpt)}
            point |= {"val": summary["score_mean"], "val_median": summary["score_median_rollout"]}
            points.append(point)
            rows.append(row(name, point))
        if args.human_final:
            human = score(ckpts[-1], "human", 0, args.out / run.name / f"human-{ckpts[-1].name}", 8, args.workers)
            points[-1] |= {"human": human["score_mean"], "human_median": human["score_median_rollout"]}
        curves[name] = points
    return curves, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path)
    parser.add_argument("--replot", type=Path, nargs="*", default=[], help="results.json files to draw together")
    parser.add_argument("--val", type=Path, default=Path("data/draw/val.zarr"), help="validation store (made once)")
    parser.add_argument("--num-tasks", type=int, default=20, help="validation tasks evaluated")
    parser.add_argument("--rollouts", type=int, default=4, help="rollouts per validation task")
    parser.add_argument("--human-final", action="store_true", help="also score each run's last checkpoint on human")
    parser.add_argument("--at", type=int, nargs="*", default=[], help="score only the checkpoints of these steps")
    parser.add_argument("--workers", type=int, default=1, help="evaluation processes")
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/draw_curves"))
    args = parser.parse_args()
    if bool(args.runs) == bool(args.replot):
        parser.error("give training runs to score, or --replot with results.json files, not both")
    curves, rows = replot(args.replot) if args.replot else score_runs(args)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out / "results.json", curves)
    header = ["run", "step", "train min", "validation mean (px)", "validation median rollout (px)"]
    table = markdown_table(header, rows)
    finals = [f"- {n}: unseen human drawings {p[-1]['human']:.2f} px" for n, p in curves.items() if "human" in p[-1]]
    (args.out / "table.md").write_text(table + ("\n" + "\n".join(finals) + "\n" if finals else ""))
    plot(curves, args.out / "curves.png")
    print(table, *finals, f"wrote {args.out / 'table.md'}, {args.out / 'curves.png'}", sep="\n")


if __name__ == "__main__":
    main()
