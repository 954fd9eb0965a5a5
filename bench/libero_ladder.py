"""The LIBERO-Gen ladder as one table and one figure: success per rung and method, with 95% Wilson intervals.

Each entry names an evaluation's output folder (what ``bpp eval`` wrote: its ``results.json``), the rung and the
method; rollouts are pooled over the folder's tasks, and over the folders given for the same rung and method (seeds).

    python bench/libero_ladder.py --out outputs/bench/libero_ladder \\
        "a. one task, 50 demos|BPP|outputs/libero/one-task-50" "a. one task, 150 demos|BPP|outputs/libero/one-task-150"

Writes ``ladder.md`` (the table), ``ladder.png`` (the figure) and ``ladder.json`` (each row's counts) under ``--out``.
``--keep`` adds the rows of an earlier ``ladder.json`` (``docs/figures/libero_ladder.json`` keeps the figure's), so
that a new rung joins the figure without the evaluation folders of the others; an entry replaces a kept row of the
same rung and method.
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from bpp.utils import read_json, write_json_atomic  # noqa: E402

Z95 = 1.959964
GOALS = {"a": 90, "b": 70}
"""Each rung's success goal for BPP (%), by the letter its label starts with (the later rungs compare methods)."""
COLOURS = {"BPP": "tab:blue", "Language": "tab:green", "Goal-Image": "tab:orange", "ICRT": "tab:purple"}
"""A bar's colour by its method (others grey)."""


def wilson(successes: int, n: int) -> tuple[float, float]:
    """The 95% Wilson score interval of a success rate, as fractions."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def pooled(folders: list[Path]) -> dict:
    """Successes, rollouts and the failed rollouts that lifted their object or another, over `folders`' results, and
    each folder's successes (a seed's, when the folders are seeds)."""
    per_folder = [read_json(folder / "results.json", "results file")["rollouts"] for folder in folders]
    each = [sum(row["score"] >= 1.0 for row in rollouts) for rollouts in per_folder]
    failed = [row for rollouts in per_folder for row in rollouts if row["score"] < 1.0]
    return {
        "successes": sum(each),
        "rollouts": sum(map(len, per_folder)),
        "failed_lifted": sum(bool(row.get("lifted")) for row in failed),
        "failed_lifted_other": sum(bool(row.get("lifted_other")) for row in failed),
        "folders": len(folders),
        "each": each,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("entries", nargs="*", help='"rung|method|eval folder" (repeat a rung and method for seeds)')
    parser.add_argument("--keep", type=Path, help="an earlier ladder.json whose rows stay in the table and figure")
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/libero_ladder"))
    args = parser.parse_args()
    if not args.entries and not args.keep:
        parser.error("give evaluation entries, --keep with a ladder.json, or both")

    groups: dict[tuple[str, str], list[Path]] = defaultdict(list)
    for entry in args.entries:
        rung, method, folder = entry.split("|")
        groups[(rung, method)].append(Path(folder))
    stats = {(row["rung"], row["method"]): row["stats"] for row in read_json(args.keep)} if args.keep else {}
    stats |= {key: pooled(folders) for key, folders in groups.items()}
    stats = dict(sorted(stats.items(), key=lambda item: item[0][0][:1]))  # by rung, rows in their order within one

    lines = [
        "| rung | method | evaluations | success | each evaluation's | 95% interval (Wilson) | failed rollouts that "
        "lifted the object / another |",
        "| --- | --- | ---: | ---: | ---: | --- | ---: |",
    ]
    for (rung, method), s in stats.items():
        low, high = wilson(s["successes"], s["rollouts"])
        rate = s["successes"] / max(1, s["rollouts"])
        lines.append(
            f"| {rung} | {method} | {s['folders']} | {s['successes']} / {s['rollouts']} ({rate:.0%}) | "
            f"{', '.join(map(str, s['each']))} | {low:.0%}-{high:.0%} | "
            f"{s['failed_lifted']} of {s['rollouts'] - s['successes']} / {s['failed_lifted_other']} |"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ladder.md").write_text("\n".join(lines) + "\n")
    write_json_atomic(args.out / "ladder.json", [{"rung": r, "method": m, "stats": s} for (r, m), s in stats.items()])
    print("\n".join(lines))

    fig, ax = plt.subplots(figsize=(max(4.5, 1.6 + 1.4 * len(stats)), 3.8))
    for i, ((rung, method), s) in enumerate(stats.items()):
        rate = s["successes"] / max(1, s["rollouts"])
        low, high = wilson(s["successes"], s["rollouts"])
        ax.bar(i, 100 * rate, color=COLOURS.get(method, "tab:grey"), alpha=0.8)
        below, above = max(0.0, rate - low), max(0.0, high - rate)  # 0 successes: the bound may round above 0
        ax.errorbar(i, 100 * rate, yerr=[[100 * below], [100 * above]], color="black", capsize=4)
        goal = GOALS.get(rung[:1])
        if goal is not None and method == "BPP":  # the rungs' goals are BPP's
            ax.hlines(goal, i - 0.45, i + 0.45, color="tab:red", linestyle="--", linewidth=1.2)
    ax.set_xticks(range(len(stats)), [f"{rung}\n{method}" for rung, method in stats], fontsize=8)
    ax.set_ylabel("success (%), 95% Wilson interval")
    ax.set_ylim(0, 100)
    ax.set_title("LIBERO-Gen ladder\n(LIBERO's predicates; dashed: the rung's goal)", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out / "ladder.png", dpi=120)
    print(f"wrote {args.out / 'ladder.md'}, {args.out / 'ladder.png'} and {args.out / 'ladder.json'}")


if __name__ == "__main__":
    main()
