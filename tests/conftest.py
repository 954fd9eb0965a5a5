from dataclasses import replace

import numpy as np
import pytest

from bpp.envs.draw.dataset import PRESETS, generate


@pytest.fixture(scope="session")
def debug_store(tmp_path_factory):
    """A tiny procedural DrawAnything store (12 tasks x 3 demos), generated once per test session."""
    return generate(PRESETS["debug"], tmp_path_factory.mktemp("data") / "debug.zarr", workers=1, progress=False)


@pytest.fixture(scope="session")
def described_store(tmp_path_factory):
    """A tiny procedural store whose tasks carry instructions (6 tasks x 2 demos)."""
    cfg = replace(PRESETS["debug"], num_tasks=6, demos_per_task=2, describe=True)
    return generate(cfg, tmp_path_factory.mktemp("data") / "described.zarr", workers=1, progress=False)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
