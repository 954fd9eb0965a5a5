"""Every method's debug and CPU size presets, with each DrawAnything observation preset the CPU presets are used
with, build and train one step (the paper presets are too large for the suite; BPP's is checked for size in
test_bpp)."""

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import PRESETS as DATA_PRESETS
from bpp.benchmarks.draw.dataset import generate
from bpp.data.prompt_dataset import PromptBatchDataset
from bpp.policies.registry import METHODS, get_method
from bpp.utils import from_dict, to_dict, to_torch
from helpers import DRAW_FRAMES

SETTINGS = [
    ("debug", "canvas"),
    ("cpu", "canvas"),
    ("cpu", "canvas-ink"),
    ("cpu", "board"),
    ("cpu", "board-view"),
    ("cpu", "image64"),
]
CASES = [(m, size, obs) for m in METHODS for size, obs in SETTINGS]
SAVED_CONFIGS = Path(__file__).parent / "data" / "method_configs.json"
"""Every method's model config as runs and checkpoints save it (JSON): each size preset with one observation preset."""


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Two tasks with instructions, so that every method (Language too) can draw batches from it."""
    cfg = replace(DATA_PRESETS["debug"], num_tasks=2, demos_per_task=2, describe=True)
    return generate(cfg, tmp_path_factory.mktemp("data") / "presets.zarr", workers=1, progress=False)


@pytest.mark.parametrize(("method", "size", "obs"), CASES, ids=["-".join(c) for c in CASES])
def test_preset_builds_and_takes_a_finite_loss(store, method, size, obs):
    torch.manual_seed(0)
    m = get_method(method)
    cfg = m.config(size, obs, BENCHMARK)
    model = m.model_cls(cfg, store.stats)
    spec = model.data_spec()
    assert set(spec.image_keys) == set(cfg.obs.image_keys)
    batch = to_torch(PromptBatchDataset(store, spec, frames=DRAW_FRAMES, batch_size=2, seed=0)[0], "cpu")
    loss = model(batch, torch.Generator().manual_seed(0))
    assert loss.ndim == 0 and math.isfinite(loss.item())


def test_canvas_ink_is_canvas_with_the_ink_on_it():
    canvas, ink = BENCHMARK.observations["canvas"], BENCHMARK.observations["canvas-ink"]
    assert ink.lowdim_keys == canvas.lowdim_keys and ink.action_key == canvas.action_key == "action"
    assert ink.proprio_keys == (*canvas.proprio_keys, "ink_length")


def test_board_view_is_board_image_with_the_ink_only_in_its_view():
    image, view = BENCHMARK.observations["board-image"], BENCHMARK.observations["board-view"]
    assert view.image_keys == image.image_keys == ("board_image",) and view.image_size == image.image_size
    assert view.action_key == image.action_key == "action_on_board"
    assert image.proprio_keys == (*view.proprio_keys, "ink_length")


def test_saved_configs_keep_their_fields():
    """What a run saves of its model config is the stored expectation, field for field, and rebuilds the same config:
    the config classes' code can change without changing what runs and checkpoints record."""
    expected = json.loads(SAVED_CONFIGS.read_text())
    built = {}
    for name in METHODS:
        method = get_method(name)
        for size, obs in (("debug", "canvas"), ("cpu", "canvas-ink"), ("paper", "paper")):
            cfg = method.config(size, obs, BENCHMARK)
            saved = json.loads(json.dumps(to_dict(cfg)))
            built[f"{name}/{size}/{obs}"] = saved
            assert from_dict(method.config_cls, saved) == cfg
    assert built == expected
