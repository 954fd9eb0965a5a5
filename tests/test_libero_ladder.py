"""``bench/libero_ladder.py``: the ladder's table from evaluation folders, with ``--keep`` the rows of an earlier
``ladder.json`` beside them (the figure's counts are kept in ``docs/figures/libero_ladder.json``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "libero_ladder.py"


def _evaluation(folder: Path, scores: list[float], lifted: list[bool]) -> str:
    folder.mkdir(parents=True)
    rows = [{"score": s, "lifted": float(up), "lifted_other": 0.0} for s, up in zip(scores, lifted, strict=True)]
    (folder / "results.json").write_text(json.dumps({"rollouts": rows}))
    return str(folder)


def _ladder(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, cwd=ROOT)


def test_kept_rows_stay_and_an_entry_replaces_its_own(tmp_path):
    first = tmp_path / "first"
    seed0 = _evaluation(tmp_path / "a0", [1.0, 1.0, 0.0, 1.0], [True, True, True, True])
    seed1 = _evaluation(tmp_path / "a1", [1.0, 0.0, 0.0, 1.0], [True, False, True, True])
    chain = _evaluation(tmp_path / "d0", [0.0, 0.0], [False, True])
    done = _ladder(f"a. one task|BPP|{seed0}", f"a. one task|BPP|{seed1}", f"d. chain|BPP|{chain}", "--out", str(first))
    assert done.returncode == 0, done.stderr
    assert "| a. one task | BPP | 2 | 5 / 8 (62%) | 3, 2 | 31%-86% | 2 of 3 / 0 |" in (first / "ladder.md").read_text()

    # Later, without the first folders: a new rung joins the kept rows (sorted by rung), a kept row is replaced.
    for folder in (seed0, seed1, chain):
        (Path(folder) / "results.json").unlink()
    unseen = _evaluation(tmp_path / "c0", [1.0, 0.0], [True, False])
    again = _evaluation(tmp_path / "d1", [1.0, 1.0], [True, True])
    second = tmp_path / "second"
    done = _ladder("--keep", str(first / "ladder.json"), f"d. chain|BPP|{again}", f"c. unseen|ICRT|{unseen}", "--out",
                   str(second))  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = [
        line for line in (second / "ladder.md").read_text().splitlines() if line.startswith("| ") and "---" not in line
    ]
    assert [row.split(" | ")[0] for row in rows[1:]] == ["| a. one task", "| c. unseen", "| d. chain"]
    assert "| d. chain | BPP | 1 | 2 / 2 (100%) |" in rows[3]
    assert (second / "ladder.png").stat().st_size > 5_000
    assert json.loads((second / "ladder.json").read_text())[0]["stats"]["each"] == [3, 2]


def test_nothing_to_draw_is_refused(tmp_path):
    done = _ladder("--out", str(tmp_path / "out"))
    assert done.returncode == 2
    assert "--keep" in done.stderr
