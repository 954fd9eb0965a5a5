"""``bench/draw_view_ablation.py``: the board's view frozen at each rollout's first frame, while the rollout inks."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np

from bpp.benchmarks.draw.env import DrawEnv

ROOT = Path(__file__).resolve().parents[1]


def _views(env: DrawEnv, cursor: tuple[float, float]) -> list[np.ndarray]:
    obs, _ = env.reset(seed=0, options={"board_angle": 0.3, "cursor": cursor})
    views = [obs["board_image"]]
    for target in [(300, 150), (300, 300), (150, 300)]:
        obs, *_ = env.step(np.array([*target, 1.0]))
        views.append(obs["board_image"])
    return views


def test_a_frozen_view_shows_each_rollout_its_first_frame(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    ablation = importlib.import_module("draw_view_ablation")
    for name in ("_observation", "reset"):
        monkeypatch.setattr(DrawEnv, name, getattr(DrawEnv, name))  # put back after the test
    env = DrawEnv(image_size=32, cameras=("board_image",))
    rendered = _views(env, (150.0, 150.0))
    assert any((view != rendered[0]).any() for view in rendered[1:])  # the ink and the cursor move in the view
    ablation.freeze_the_view()
    frozen = _views(env, (150.0, 150.0))
    assert all((view == rendered[0]).all() for view in frozen)
    moved = _views(env, (200.0, 200.0))  # a new rollout: its own first frame, frozen in turn
    assert (moved[0] != rendered[0]).any() and all((view == moved[0]).all() for view in moved)
