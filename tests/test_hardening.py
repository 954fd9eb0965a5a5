"""Inputs a careful user or an attacker might give: refused with a message naming the input, or handled safely."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bpp.train import TrainConfig, train
from helpers import config


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("grad_clip", -1.0),
        ("grad_clip", 0.0),
        ("ema_decay", 1.0),
        ("ema_decay", -0.1),
        ("save_every", 0),
        ("log_every", 0),
        ("lr", 0.0),
        ("warmup_steps", -1),
        ("tasks_per_batch", 0),
        ("workers", -2),
        ("frame_cache_gb", -1.0),
    ],
)
def test_training_settings_out_of_range_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"^{field} must be .*got {value!r}"):
        TrainConfig(data=Path("x.zarr"), **{field: value})


def _bpp(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "bpp.cli", *args], capture_output=True, text=True, timeout=300, cwd=cwd
    )


def test_eval_of_a_missing_checkpoint_writes_nothing(tmp_path):
    out = _bpp("eval", str(tmp_path / "typo"), "--data-dir", str(tmp_path / "data"), "--out", str(tmp_path / "eval"))
    assert out.returncode != 0 and "typo: no such checkpoint" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "data").exists() and not (tmp_path / "eval").exists()


def test_task_ids_never_become_paths_outside_the_output_folder(debug_store, tmp_path):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    drawing = tmp_path / "evil.json"
    strokes = [[[0.2, 0.2], [0.8, 0.2], [0.5, 0.8]]]
    drawing.write_text(json.dumps({"drawings": [{"id": "x/../../../pwn", "strokes": strokes}]}))
    out = tmp_path / "a" / "b" / "eval"
    args = ("--files", str(drawing), "--rollouts", "1", "--max-steps", "12", "--workers", "1", "--videos", "1")
    result = _bpp("eval", str(run), *args, "--out", str(out), "--data-dir", str(tmp_path / "data"))
    assert result.returncode == 0, result.stderr[-2000:]
    videos = list(out.glob("rollout_*"))
    assert len(videos) == 1 and "/" not in videos[0].name[len("rollout_") :]
    assert not list(tmp_path.rglob("pwn*"))


def test_resume_refuses_settings_other_than_the_runs_own(debug_store, tmp_path):
    from dataclasses import replace

    cfg = TrainConfig(data=debug_store.path, out=tmp_path / "run", steps=2, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    resume = replace(cfg, resume=True)
    for changed, model, field in (
        (replace(resume, seed=1), config("bpp"), "train_config.seed: 0 in the run, 1 now"),
        (replace(resume, steps=4), config("bpp"), "train_config.steps: 2 in the run, 4 now"),
        (resume, config("bpp", dim=64, heads=2), "model_config.dim: 32 in the run, 64 now"),
    ):
        with pytest.raises(ValueError, match=field):
            train(changed, model, progress=False)
    before = (tmp_path / "run" / "config.json").read_text()
    train(resume, config("bpp"), progress=False)  # the same settings: resumes (nothing left to do)
    assert (tmp_path / "run" / "config.json").read_text() == before


def test_overwrite_replaces_only_a_store(tmp_path, debug_store):
    from bpp.data.store import EpisodeStore, StoreError
    from bpp.envs.draw.dataset import PRESETS, generate

    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("years of work")
    with pytest.raises(StoreError, match="is not an episode store; only a store is ever replaced"):
        generate(PRESETS["debug"], precious, workers=1, overwrite=True, progress=False)
    assert (precious / "chapter1.tex").read_text() == "years of work"
    out = _bpp("draw", "generate", "--preset", "debug", "--out", str(precious), "--overwrite")
    assert out.returncode != 0 and "not an episode store" in out.stderr and (precious / "chapter1.tex").exists()
    store = tmp_path / "store.zarr"
    generate(PRESETS["debug"], store, workers=1, progress=False)
    again = generate(PRESETS["debug"], store, workers=1, overwrite=True, progress=False)  # a store is replaced
    assert EpisodeStore(again.path).num_tasks == debug_store.num_tasks


def test_interrupted_writers_leave_no_hidden_folders_behind(tmp_path):
    import os
    import time

    from bpp.envs.draw.dataset import PRESETS, generate

    store = tmp_path / "d.zarr"
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = tmp_path / f".d.zarr.partial-{int(finished.stdout)}-0123abcd"  # a writer that was killed
    alive = tmp_path / f".d.zarr.partial-{os.getpid()}-4567ef01"  # a writer still running (this process)
    legacy = tmp_path / ".d.zarr.partial-89abcdef"  # an older version's name, untouched for two hours
    for folder in (dead, alive, legacy):
        folder.mkdir()
    os.utime(legacy, (time.time() - 7200, time.time() - 7200))
    generate(PRESETS["debug"], store, workers=1, progress=False)
    assert not dead.exists() and not legacy.exists() and alive.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, "d.zarr"])


def test_runs_with_a_damaged_newest_checkpoint_resume_from_the_newest_intact_one(debug_store, tmp_path, capsys):
    from dataclasses import replace

    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, steps=4, batch_size=4, workers=0, warmup_steps=1, save_every=2)
    train(cfg, config("bpp"), progress=False)
    checkpoints = run / "checkpoints"
    weights = checkpoints / "step_00000004" / "ema.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])  # truncated, as by a full disk
    quick = ("--tasks", str(debug_store.path), "--num-tasks", "1", "--rollouts", "1", "--max-steps", "5")
    out = _bpp("eval", str(run), *quick, "--out", str(tmp_path / "eval"))
    assert out.returncode != 0 and "ema.safetensors: unreadable weights" in out.stderr and "Traceback" not in out.stderr
    capsys.readouterr()
    more = replace(cfg, resume=True)
    train(more, config("bpp"), progress=False)  # the run's own settings: resumes from step 2, saves step 4 again
    err = capsys.readouterr().err
    assert "skipping step_00000004" in err and "ema.safetensors: unreadable weights" in err
    assert "resuming from step_00000002" in err
    (checkpoints / "last").write_text("step_00000009")  # a pointer to a folder that is gone
    from bpp.checkpoint import resolve_checkpoint

    assert resolve_checkpoint(run).name == "step_00000004"
    assert "names step_00000009, which is missing" in capsys.readouterr().err
    (checkpoints / "step_00000004" / "state.json").write_text('{"format": "bpp-check')  # truncated JSON
    out = _bpp("eval", str(run), *quick, "--out", str(tmp_path / "eval"))
    assert out.returncode != 0 and "state.json: not valid JSON" in out.stderr and "Traceback" not in out.stderr
