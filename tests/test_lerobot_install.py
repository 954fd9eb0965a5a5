"""bpp installs into the environment of a LeRobot user. `make install-all` builds LeRobot's environment as such a
user has it: a new virtual environment, LeRobot first (lerobot-first.txt records what it installed), then bpp with its
lerobot extra on top (bpp-plan.json records what a plain `pip install -e .[lerobot]`, without bpp's constraints,
would have installed at that point). Here, in that environment: bpp changed none of LeRobot's packages and a plain
install would not have either, every requirement of LeRobot and of bpp holds, and the `bpp` command exports a store
to a dataset that LeRobot's own loader reads and imports it back."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from bpp.data.store import EpisodeStore
from helpers import OPTIONAL_PARTS, REQUIRE_ALL

pytestmark = pytest.mark.lerobot

ENVIRONMENT = Path(sys.prefix)
FIRST = ENVIRONMENT / "lerobot-first.txt"
PLAN = ENVIRONMENT / "bpp-plan.json"


def _name(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _records() -> tuple[dict[str, str], dict[str, str]]:
    """What LeRobot installed (name -> version) and what a plain install of bpp would have installed after it."""
    if not (FIRST.is_file() and PLAN.is_file()):
        why = f"{FIRST} and {PLAN} are written when {ENVIRONMENT} is built: {OPTIONAL_PARTS['lerobot'][1]}"
        if REQUIRE_ALL:
            pytest.fail(why)
        pytest.skip(why)
    first = dict(line.strip().split("==", 1) for line in FIRST.read_text().splitlines() if "==" in line)
    plan = [item["metadata"] for item in json.loads(PLAN.read_text())["install"]]
    return {_name(k): v for k, v in first.items()}, {_name(m["name"]): m["version"] for m in plan}


def _requirements_hold(distribution: str, extras: tuple[str, ...] = ("",)) -> list[str]:
    """The requirements of `distribution` (with `extras`) that the installed versions do not meet."""
    from packaging.requirements import Requirement

    unmet = []
    for text in metadata.requires(distribution) or []:
        requirement = Requirement(text)
        if requirement.marker and not any(requirement.marker.evaluate({"extra": e}) for e in extras):
            continue
        try:
            installed = metadata.version(requirement.name)
        except metadata.PackageNotFoundError:
            unmet.append(f"{requirement}: not installed")
            continue
        if not requirement.specifier.contains(installed, prereleases=True):
            unmet.append(f"{requirement}: {installed} installed")
    return unmet


def test_bpp_on_top_of_lerobot_changes_none_of_its_packages():
    first, plan = _records()
    assert "lerobot" in first and "torch" in first
    now = {_name(d.metadata["Name"]): d.version for d in metadata.distributions()}
    changed = {name: (version, now.get(name)) for name, version in first.items() if now.get(name) != version}
    assert not changed, f"installing bpp changed LeRobot's packages (before, after): {changed}"
    assert "bpp" in plan
    replaced = {name: (first[name], plan[name]) for name in plan if name in first}
    assert not replaced, f"a plain pip install -e .[lerobot] would replace LeRobot's packages: {replaced}"
    assert _requirements_hold("lerobot") == []  # torch < 2.11 among them
    assert _requirements_hold("bpp", ("", "lerobot")) == []  # bpp's ranges take LeRobot's torch
    assert metadata.version("lerobot") == first["lerobot"]


@pytest.mark.slow
def test_the_bpp_command_exports_a_dataset_lerobot_loads_and_imports_it_back(debug_store, tmp_path, monkeypatch):
    import datasets

    from bpp.benchmarks.lerobot.library import offline_and_quiet

    monkeypatch.setattr(datasets.config, "HF_DATASETS_CACHE", tmp_path / "datasets-cache")
    env = {**os.environ, "HF_DATASETS_CACHE": str(tmp_path / "datasets-cache"), "HF_HUB_OFFLINE": "1"}
    bpp = str(ENVIRONMENT / "bin" / "bpp")
    out, back = tmp_path / "draw", tmp_path / "back.zarr"
    for argv in (
        ["lerobot", "export", str(debug_store.path), "--out", str(out), "--episodes", "0:3", "--image-size", "32"],
        ["lerobot", "import", str(out), "--out", str(back), "--image-size", "32"],
    ):
        result = subprocess.run([bpp, *argv], capture_output=True, text=True, env=env, timeout=600)
        assert result.returncode == 0, result.stderr[-3000:]
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # LeRobot's own module, as its users import it

    with offline_and_quiet(out):
        dataset = LeRobotDataset("bpp/draw", root=out, video_backend="pyav")
    n = int(debug_store.episode_ends[2])
    assert dataset.num_episodes == 3 and dataset.num_frames == n and dataset.fps == 10
    actions = np.asarray(dataset.hf_dataset.with_format("arrow")[:].column("action").to_pylist())
    np.testing.assert_array_equal(actions.reshape(n, -1), debug_store.array("action")[:n].reshape(n, -1))
    imported = EpisodeStore(back)
    assert imported.num_episodes == 3
    for key in debug_store.keys:
        np.testing.assert_array_equal(imported.array(key), debug_store.array(key)[:n], err_msg=key)
