"""Shared fixtures, and one torch thread budget per test process.

`make test` runs the files on every core at once (pytest-xdist, one file per worker at a time). Two processes that
each spin two OpenMP threads on two cores run many times slower than one each, so under xdist every worker, and
every `bpp` process a test starts, gets an equal share of the cores (``OMP_NUM_THREADS``) unless the user set it.
"""

import os

_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1 and not os.environ.get("OMP_NUM_THREADS"):
    os.environ["OMP_NUM_THREADS"] = str(max(1, len(os.sched_getaffinity(0)) // _WORKERS))

from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from bpp.envs.draw.dataset import PRESETS, generate  # noqa: E402

if _WORKERS > 1:  # in case torch was imported before this file
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


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
