"""How two policies differ on the same tasks: the difference of their scores paired task by task.

    python bench/paired.py outputs/icrt/results.json outputs/bpp/results.json
    python bench/paired.py a0/results.json,a1/results.json b0/results.json,b1/results.json --without hershey-trefoil

Each side is one ``bpp eval`` results.json, or several separated by commas (e.g. one per seed: each task's score is
then its mean over them). Prints both means, B minus A with its standard error over the tasks both scored, B / A, and
on how many tasks B is better (the metric's direction read from the results). When both sides list as many files (one
per seed, in the same order), it also prints each seed's paired difference and their mean ± std over seeds. When a side
lists several, it also prints a 95% interval for B minus A that counts both sources of spread: each draw resamples
each side's seeds and the tasks (the same tasks for both sides, so the pairing is kept), with replacement.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from common import paired, task_means


def read_scores(paths: list[Path]) -> tuple[list[dict[str, float]], dict]:
    """Each evaluation's task scores (a task's mean over rollouts) from ``bpp eval``'s results.json files `paths` (e.g.
    one per seed, all of the same tasks), and their metric."""
    results = [json.loads(Path(path).read_text()) for path in paths]
    tasks = [task_means(r) for r in results]
    if any(t.keys() != tasks[0].keys() for t in tasks):
        raise ValueError(f"{', '.join(map(str, paths))}: the evaluations scored different tasks")
    return tasks, results[0]["metric"]


def averaged(evaluations: list[dict[str, float]]) -> dict[str, float]:
    """Each task's score averaged over the evaluations (e.g. its seeds)."""
    return {task: float(np.mean([scores[task] for scores in evaluations])) for task in evaluations[0]}


def without(scores: dict[str, float], tasks: list[str]) -> dict[str, float]:
    """`scores` less the task ids `tasks`."""
    return {task: score for task, score in scores.items() if task not in tasks}


def resampled(
    seeds_a: list[dict[str, float]], seeds_b: list[dict[str, float]], tasks: list[str], draws: int, seed: int = 0
) -> np.ndarray:
    """B minus A's mean score in each of `draws` resamplings of both sides' evaluations (seeds) and of `tasks`."""
    a, b = (np.array([[scores[task] for task in tasks] for scores in side]) for side in (seeds_a, seeds_b))
    rng = np.random.default_rng(seed)
    out = np.empty(draws)
    for draw in range(draws):
        columns = rng.integers(0, len(tasks), len(tasks))
        rows_a, rows_b = rng.integers(0, len(a), len(a)), rng.integers(0, len(b), len(b))
        out[draw] = b[rows_b][:, columns].mean() - a[rows_a][:, columns].mean()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", help="results.json of A (comma-separated: averaged task by task)")
    parser.add_argument("b", help="results.json of B (comma-separated: averaged task by task)")
    parser.add_argument("--without", nargs="+", default=[], metavar="TASK_ID", help="task ids to leave out")
    parser.add_argument("--draws", type=int, default=10_000, help="resamplings of seeds and tasks for the interval")
    args = parser.parse_args()
    try:
        (seeds_a, metric), (seeds_b, _) = (read_scores([Path(p) for p in side.split(",")]) for side in (args.a, args.b))
        lower = metric["lower_is_better"]
        result = paired(without(averaged(seeds_a), args.without), without(averaged(seeds_b), args.without), lower)
        by_seed = []
        if len(seeds_a) == len(seeds_b) > 1:
            pairs = zip(seeds_a, seeds_b, strict=True)
            by_seed = [paired(without(a, args.without), without(b, args.without), lower) for a, b in pairs]
        draws = np.empty(0)  # an interval only where a side has several seeds
        if max(len(seeds_a), len(seeds_b)) > 1:
            tasks = sorted(without(seeds_a[0], args.without).keys() & seeds_b[0].keys())
            draws = resampled(seeds_a, seeds_b, tasks, args.draws)
    except (OSError, ValueError, KeyError) as error:  # a missing or unreadable file, tasks that do not match
        parser.error(f"{type(error).__name__}: {error}")
    unit = f" {metric['unit']}" if metric.get("unit") else ""
    ratio = f"{result.mean_b / result.mean_a:.3f}" if result.mean_a else "undefined"
    print(
        f"{metric['name']} over {result.tasks} tasks: A {result.mean_a:.2f}, B {result.mean_b:.2f}{unit}; "
        f"B minus A {result}{unit} (± s.e.m.), B / A {ratio}; B better on {result.b_better} of {result.tasks}"
    )
    if by_seed:
        diffs = np.array([seed.diff for seed in by_seed])
        print(
            f"by seed, B minus A: {', '.join(f'{seed} (B better on {seed.b_better})' for seed in by_seed)}; "
            f"over seeds {diffs.mean():+.2f} ± {diffs.std(ddof=1):.2f}{unit} (± std)"
        )
    if draws.size:
        low, high = np.percentile(draws, [2.5, 97.5])
        better = np.mean(draws < 0 if lower else draws > 0)
        print(
            f"resampling seeds and tasks ({len(draws)} draws): B minus A 95% interval {low:+.2f} to {high:+.2f}{unit}; "
            f"B better in {better:.1%} of draws"
        )


if __name__ == "__main__":
    main()
