"""``bench/paired.py``: two evaluations' difference paired task by task, seeds averaged, in the metric's direction."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "paired.py"
CHAMFER = {"name": "Chamfer distance", "unit": "px", "lower_is_better": True}
SUCCESS = {"name": "success", "unit": "", "lower_is_better": False}


def _results(path: Path, scores: dict[str, float], metric: dict = CHAMFER) -> str:
    tasks = [{"task": i, "task_id": task, "score_mean": score} for i, (task, score) in enumerate(scores.items())]
    path.write_text(json.dumps({"metric": metric, "tasks": tasks}))
    return str(path)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, cwd=ROOT)


def _run_seeds(tmp_path: Path, a: list[dict[str, float]], b: list[dict[str, float]], *args: str) -> str:
    """The script on one results.json per seed a side (a0.json, a1.json, ... and b0.json, ...); its output, once it
    has succeeded."""
    sides = (
        ",".join(_results(tmp_path / f"{side}{seed}.json", each) for seed, each in enumerate(scores))
        for side, scores in (("a", a), ("b", b))
    )
    done = _run(*sides, *args)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_seeds_are_averaged_per_task_before_pairing(tmp_path):
    a = _results(tmp_path / "a.json", {"x": 10.0, "y": 20.0, "z": 30.0})
    b0 = _results(tmp_path / "b0.json", {"x": 6.0, "y": 22.0, "z": 26.0})
    b1 = _results(tmp_path / "b1.json", {"x": 8.0, "y": 24.0, "z": 28.0})
    done = _run(a, f"{b0},{b1}")
    assert done.returncode == 0, done.stderr
    # B per task: 7, 23, 27; differences -3, +3, -3: mean -1, s.e.m. sqrt((4 + 16 + 4) / 2 / 3) = 2
    assert "over 3 tasks: A 20.00, B 19.00 px; B minus A -1.00 ± 2.00 px" in done.stdout
    assert "B / A 0.950; B better on 2 of 3" in done.stdout
    assert "by seed" not in done.stdout  # one evaluation against two: no seed to pair with


def test_as_many_seeds_a_side_are_also_paired_seed_by_seed(tmp_path):
    a = [{"x": 10.0, "y": 20.0}, {"x": 12.0, "y": 20.0}]
    out = _run_seeds(tmp_path, a, [{"x": 9.0, "y": 19.0}, {"x": 15.0, "y": 23.0}], "--without", "y")
    # seed 0: x 10 -> 9, -1; seed 1: x 12 -> 15, +3; over seeds +1 ± std(-1, 3) = 2.83
    assert "by seed, B minus A: -1.00 ± 0.00 (B better on 1), +3.00 ± 0.00 (B better on 0)" in out
    assert "over seeds +1.00 ± 2.83 px (± std)" in out


def test_without_leaves_tasks_out(tmp_path):
    a = _results(tmp_path / "a.json", {"x": 10.0, "y": 20.0, "z": 30.0})
    b = _results(tmp_path / "b.json", {"x": 6.0, "y": 22.0, "z": 26.0})
    done = _run(a, b, "--without", "y")
    assert done.returncode == 0, done.stderr
    assert "over 2 tasks: A 20.00, B 16.00 px; B minus A -4.00 ± 0.00 px" in done.stdout


def test_higher_is_better_counts_the_other_way(tmp_path):
    a = _results(tmp_path / "a.json", {"t0": 0.5, "t1": 0.9}, SUCCESS)
    b = _results(tmp_path / "b.json", {"t0": 0.7, "t1": 0.8}, SUCCESS)
    done = _run(a, b)
    assert done.returncode == 0, done.stderr
    assert "B better on 1 of 2" in done.stdout and "B minus A +0.05" in done.stdout


def test_seeds_of_different_tasks_are_refused(tmp_path):
    a = _results(tmp_path / "a.json", {"x": 1.0})
    b0 = _results(tmp_path / "b0.json", {"x": 1.0})
    b1 = _results(tmp_path / "b1.json", {"y": 1.0})
    done = _run(a, f"{b0},{b1}")
    assert done.returncode != 0
    assert "scored different tasks" in done.stderr


def test_the_interval_over_seeds_and_tasks_is_the_point_when_seeds_agree(tmp_path):
    a, b = [{"x": 10.0, "y": 20.0}] * 2, [{"x": 8.0, "y": 18.0}] * 2
    out = _run_seeds(tmp_path, a, b, "--draws", "200")
    assert "(200 draws): B minus A 95% interval -2.00 to -2.00 px; B better in 100.0% of draws" in out


def test_the_interval_spans_what_the_seeds_disagree_on(tmp_path):
    # A's two seeds agree; B's differ by 10 px: a draw takes B's seed 0 twice (-5), once each (0) or seed 1 twice (+5)
    out = _run_seeds(tmp_path, [{"x": 10.0}] * 2, [{"x": 5.0}, {"x": 15.0}])
    assert "B minus A 95% interval -5.00 to +5.00 px" in out
    better = float(out.split("B better in ")[1].split("%")[0])
    assert 23.0 < better < 27.0  # a quarter of the draws take seed 0 twice
