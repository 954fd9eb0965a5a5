"""How two policies differ on the same tasks: the difference of their scores paired task by task.

    python bench/paired.py outputs/icrt/results.json outputs/bpp/results.json
    python bench/paired.py a0/results.json,a1/results.json b0/results.json,b1/results.json --without hershey-trefoil

Each side is one ``bpp eval`` results.json, or several separated by commas (e.g. one per seed: each task's score is
then its mean over them). Prints both means, B minus A with its standard error over the tasks both scored, B / A, and
on how many tasks B is better (the metric's direction read from the results).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from common import paired


def task_scores(paths: list[Path]) -> tuple[dict[str, float], dict]:
    """Each task's score (its mean over rollouts) averaged over the evaluations `paths` (``bpp eval``'s results.json,
    e.g. one per seed, all of the same tasks), and their metric."""
    results = [json.loads(Path(path).read_text()) for path in paths]
    tasks = [{t["task_id"]: t["score_mean"] for t in r["tasks"]} for r in results]
    if any(t.keys() != tasks[0].keys() for t in tasks):
        raise ValueError(f"{', '.join(map(str, paths))}: the evaluations scored different tasks")
    return {task: float(np.mean([t[task] for t in tasks])) for task in tasks[0]}, results[0]["metric"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", help="results.json of A (comma-separated: averaged task by task)")
    parser.add_argument("b", help="results.json of B (comma-separated: averaged task by task)")
    parser.add_argument("--without", nargs="+", default=[], metavar="TASK_ID", help="task ids to leave out")
    args = parser.parse_args()
    try:
        (a, metric), (b, _) = (task_scores([Path(p) for p in side.split(",")]) for side in (args.a, args.b))
        for task in args.without:
            a.pop(task, None)
            b.pop(task, None)
        result = paired(a, b, metric["lower_is_better"])
    except (OSError, ValueError, KeyError) as error:  # a missing or unreadable file, tasks that do not match
        parser.error(f"{type(error).__name__}: {error}")
    unit = f" {metric['unit']}" if metric.get("unit") else ""
    ratio = f"{result.mean_b / result.mean_a:.3f}" if result.mean_a else "undefined"
    print(
        f"{metric['name']} over {result.tasks} tasks: A {result.mean_a:.2f}, B {result.mean_b:.2f}{unit}; "
        f"B minus A {result}{unit} (± s.e.m.), B / A {ratio}; B better on {result.b_better} of {result.tasks}"
    )


if __name__ == "__main__":
    main()
