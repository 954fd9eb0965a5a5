"""The benchmark contract: generic layers import no benchmark, and a second benchmark (toy_reach, 2-D reaching)
generates, trains, evaluates and reports through the same commands as DrawAnything."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bpp
from bpp.cli import main
from bpp.core.registry import BENCHMARKS, get_benchmark, register_benchmark
from bpp.data.store import EpisodeStore
from bpp.evaluation.evaluate import Protocol

SRC = Path(bpp.__file__).parent
SHARED_BY_BENCHMARKS = ("benchmarks", "drawing", "recorded")
"""The benchmarks, and what some of them share: the drawing benchmarks' drawings and metric, recorded demonstrations'
open-loop evaluation."""
GENERIC = [
    p
    for p in SRC.rglob("*.py")
    if p.relative_to(SRC).parts[0] not in SHARED_BY_BENCHMARKS and p != SRC / "core" / "registry.py"
]
"""The core (the contract, prompted rollouts, poses) and the generic layers: data, nn, policies, training, checkpoints,
evaluation, serving, the command line. The registry, core/registry.py, is where benchmarks are named."""
DRAW_VOCABULARY = ["cursor_on_board", "action_on_board", "ink_length", "pen_down", "board_angle", "chamfer", "hershey"]


def _benchmark_folders() -> dict[str, str]:
    """Registered built-in benchmark name -> its folder under bpp/benchmarks/."""
    return {
        name: target.split(":")[0].split(".")[2] for name, target in BENCHMARKS.items() if target.startswith("bpp.")
    }


def test_generic_layers_name_no_benchmark():
    folders = _benchmark_folders()
    assert folders == {
        "drawanything": "draw",
        "libero_gen": "libero",
        "lerobot_dataset": "lerobot",
        "iphumi": "iphumi",
        "draw3d": "draw3d",
    }
    offences = []
    for path in GENERIC:
        text = path.read_text()
        for name, folder in folders.items():
            patterns = [
                rf"bpp\.benchmarks\.{folder}\b",
                rf"from bpp\.benchmarks import {folder}\b",
                rf"\b{name}\b",
                *DRAW_VOCABULARY,
            ]
            offences += [f"{path.relative_to(SRC)}: {p}" for p in patterns if re.search(p, text, re.IGNORECASE)]
    assert not offences, offences


def test_generic_modules_load_no_benchmark_at_import():
    code = (
        "import sys, bpp.cli, bpp.train, bpp.evaluation.evaluate, bpp.evaluation.report, bpp.data.prompt_dataset, "
        "bpp.policies.agent, bpp.checkpoint\n"
        "from bpp.policies.registry import METHODS, get_method\n"
        "[get_method(m) for m in METHODS]\n"
        "print([m for m in sys.modules if m.startswith('bpp.benchmarks.') and m.count('.') > 2])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_unknown_benchmarks_and_broken_plugins_are_refused():
    with pytest.raises(ValueError, match="unknown benchmark 'nope'; registered: .*drawanything"):
        get_benchmark("nope")
    with pytest.raises(TypeError, match="does not satisfy"):
        register_benchmark("broken", object())


@pytest.fixture
def reach(monkeypatch):
    import toy_reach

    monkeypatch.setitem(BENCHMARKS, "reach", "toy_reach:BENCHMARK")
    yield toy_reach.BENCHMARK
    from bpp.core import registry

    registry._LOADED.pop("reach", None)


@pytest.mark.parametrize("method", ["bpp", "icrt"])
def test_a_second_benchmark_generates_trains_evaluates_and_reports(reach, tmp_path, capsys, method):
    store, run, out = tmp_path / "reach.zarr", tmp_path / "run", tmp_path / "eval"
    main(["reach", "generate", "--preset", "debug", "--num-tasks", "4", "--out", str(store)])
    assert EpisodeStore(store).benchmark == "reach" and EpisodeStore(store).num_tasks == 4
    main(
        ["train", "--method", method, "--data", str(store), "--out", str(run), "--preset", "debug"]
        + ["--steps", "3", "--batch-size", "4", "--workers", "0"]
    )
    state = json.loads((run / "config.json").read_text())
    assert state["dataset"]["benchmark"] == "reach" and state["model_config"]["obs"]["proprio_keys"] == ["pos"]
    main(["eval", str(run), "--tasks", "train", "--rollouts", "2", "--workers", "1", "--out", str(out)])
    results = json.loads((out / "results.json").read_text())
    assert results["benchmark"] == "reach" and results["metric"]["name"] == "waypoint miss"
    assert results["summary"]["tasks"] == 4 and results["summary"]["rollouts"] == 8
    assert {"start", "score", "target_episode", "prompt_episode", "seed"} <= set(results["rollouts"][0])
    assert np.isfinite(results["summary"]["score_mean"]) and results["protocol"]["max_steps"] == reach.max_steps
    assert "waypoint miss" in (out / "results.md").read_text()
    assert (out / "grid.png").stat().st_size > 1000 and list(out.glob("rollout_reach-0.*"))
    assert "waypoint miss" in capsys.readouterr().out
    # The benchmark's conditions and the seeds are the protocol's plan, drawn from (seed, task, rollout) alone, so
    # every method and checkpoint gets the same rollouts.
    plan = [row for t in range(4) for row in Protocol(rollouts=2).plan(EpisodeStore(store), t, reach)]
    assert [(r["start"], r["seed"]) for r in results["rollouts"]] == [(p["start"], p["seed"]) for p in plan]
    with pytest.raises(SystemExit, match="no named task set|not a task set"):
        main(["eval", str(run), "--tasks", "human", "--out", str(tmp_path / "none")])
    assert not (tmp_path / "none").exists()
