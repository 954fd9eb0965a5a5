"""Shared fixtures, and one torch thread budget per test process.

`make test` runs the files on several cores at once (pytest-xdist, each file in one worker). Two processes that each
run two OpenMP threads on two cores wait on each other at every operation (this project measured a 30-fold slowdown
of training beside another busy program; BENCHMARKS.md), so under xdist every worker, and every `bpp` process a
test starts, gets an equal share of the cores (``OMP_NUM_THREADS``) unless the user set that variable.
"""

import os

_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_SHARE = None
if _WORKERS > 1 and not os.environ.get("OMP_NUM_THREADS"):
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    _SHARE = max(1, _cores // _WORKERS)
    os.environ["OMP_NUM_THREADS"] = str(_SHARE)

from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from bpp.benchmarks.draw.dataset import PRESETS, generate  # noqa: E402
from helpers import OPTIONAL_PARTS, REQUIRE_ALL, missing_parts  # noqa: E402

if _SHARE is not None:  # in case torch was imported before this file
    torch.set_num_threads(_SHARE)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Skip a test whose optional part is missing, naming what to install (under `make test`, stop instead). Runs
    after `-m` has deselected tests: `make test` runs the lerobot tests in LeRobot's environment and deselects them
    here."""
    missing = {marker: missing_parts(marker) for marker in OPTIONAL_PARTS}
    for item in items:
        for marker, absent in missing.items():
            if absent and item.get_closest_marker(marker):
                how = OPTIONAL_PARTS[marker][1]
                if REQUIRE_ALL:
                    raise pytest.UsageError(f"{item.nodeid} needs {', '.join(absent)} ({how}), which is missing")
                item.add_marker(pytest.mark.skip(reason=f"needs {', '.join(absent)}: {how}"))


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
