"""``bench/draw_curves.py --replot``: saved learning curves (one results.json per seed) drawn in one figure, without
their checkpoints."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "draw_curves.py"


def _curve(step: int, minutes: float, val: float) -> dict:
    return {"step": step, "samples": step * 64, "minutes": minutes, "val": val, "val_median": val / 2}


def test_replot_merges_saved_curves_sorted_by_name(tmp_path):
    first, second = tmp_path / "seed0.json", tmp_path / "seed1.json"
    first.write_text(json.dumps({"ICRT (icrt-s0)": [_curve(4000, 20.0, 9.0)], "BPP (bpp-s0)": [_curve(4000, 10, 30)]}))
    second.write_text(json.dumps({"BPP (bpp-s1)": [_curve(4000, 11.5, 25.25), _curve(8000, 23.0, 12.5)]}))
    out = tmp_path / "all"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--replot", str(first), str(second), "--out", str(out)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    merged = json.loads((out / "results.json").read_text())
    assert list(merged) == ["BPP (bpp-s0)", "BPP (bpp-s1)", "ICRT (icrt-s0)"]
    assert merged["BPP (bpp-s1)"][1]["val"] == 12.5
    table = (out / "table.md").read_text()
    assert "| BPP (bpp-s1) | 8000 | 23.0 | 12.50 | 6.25 |" in table
    assert (out / "curves.png").stat().st_size > 10_000


def test_replot_refuses_runs_beside_it(tmp_path):
    saved = tmp_path / "seed0.json"
    saved.write_text(json.dumps({"BPP (bpp-s0)": [_curve(4000, 10.0, 30.0)]}))
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(tmp_path), "--replot", str(saved), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 2
    assert "not both" in done.stderr
    assert not (tmp_path / "out").exists()
