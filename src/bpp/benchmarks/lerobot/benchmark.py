"""Imported LeRobot datasets as a benchmark (the contract of :mod:`bpp.benchmarks.contract`): their observation
presets, their stored camera frames, and open-loop evaluation on held-out episodes, since there is no simulator.

Stores of this benchmark come from ``bpp lerobot import``; ``bpp lerobot generate`` only says so. Nothing here
imports LeRobot's library: only the import and export commands need the ``lerobot`` extra.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bpp.benchmarks.contract import Metric, RolloutResult, TaskSet
from bpp.benchmarks.lerobot.importer import BENCHMARK as NAME
from bpp.data.spec import ObservationPreset
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.media import resize_frames

IMAGE_SIZE = 96
"""The presets' camera size (the import's default: frames are then used as stored)."""


def _robot(cameras: int, description: str) -> ObservationPreset:
    return ObservationPreset(
        proprio_keys=("state",),
        image_keys=tuple(f"camera{i}" for i in range(cameras)),
        image_size=IMAGE_SIZE,
        goal_camera="camera0",
        description=description,
    )


OBSERVATIONS: Mapping[str, ObservationPreset] = {
    "robot": _robot(
        1,
        "the robot's state (observation.state) and its first camera (camera0) at 96x96; actions as stored "
        "(--model.action-relative-to state makes them relative to the state)",
    ),
    "robot-2cam": _robot(2, "as robot, with the first two cameras (camera0, camera1)"),
    "robot-3cam": _robot(3, "as robot, with the first three cameras (camera0 to camera2)"),
    "state": ObservationPreset(
        proprio_keys=("state",),
        goal_camera="camera0",
        description="the robot's state alone (observation.state); for datasets without cameras, or CPUs",
    ),
}


@dataclass(frozen=True)
class NoGeneration:
    """LeRobot datasets are imported, not generated: this configuration has nothing to set."""


class LeRobotDatasets:
    """Demonstrations recorded as LeRobot datasets: train on them, evaluate open loop on held-out episodes."""

    name = NAME
    command = "lerobot"
    command_table = "bpp.benchmarks.lerobot.commands:COMMANDS"
    description = (
        "LeRobot v3 datasets: import one as a store (bpp lerobot import), export any store as one (bpp lerobot "
        "export); evaluated open loop by the action error on held-out episodes"
    )
    data_config = NoGeneration
    data_presets = {"debug": NoGeneration()}
    default_data_dir = Path("data/lerobot")
    derived_keys: Mapping[str, tuple[str, tuple[int, ...]]] = {}
    observations = OBSERVATIONS
    metric = Metric(
        "action error",
        lower_is_better=True,
        description=(
            "open loop on a recorded episode of the task other than the prompt: mean over its steps and action "
            "dimensions of |policy action - recorded action|, each dimension over half its range in the store"
        ),
    )
    max_steps = 1000
    """Replayed episodes are cut to this many steps."""
    task_sets: Mapping[str, str] = {}

    def default_observation(self, size: str) -> str:
        return "robot"

    def generate(self, cfg, out: Path, *, workers: int = 0, overwrite: bool = False, progress: bool = True):
        raise UserError(
            "LeRobot datasets are imported, not generated: bpp lerobot import PATH_OR_REPO_ID --out STORE "
            "(see bpp lerobot import --help)"
        )

    def frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """The camera frames imported with the store (resized if another size is asked for)."""
        cameras = list(store.config.get("cameras", []))
        if key not in cameras:
            have = f"the cameras {', '.join(cameras)}" if cameras else "no cameras (train with --obs state)"
            raise UserError(f"{store.path} has {have}; got {key!r}")
        return stored_frames(store, episode, key, size, last_only, steps)

    # ------------------------------------------------------------ evaluation
    def task_set(self, name: str, data_dir: Path, workers: int = 0) -> TaskSet:
        raise UserError(
            f"imported LeRobot datasets have no named task set {name!r}; evaluate on the held-out store the import "
            "wrote (bpp eval RUN --tasks STORE-heldout.zarr) or on the training tasks (--tasks train)"
        )

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: int = 0) -> TaskSet:
        raise UserError("imported LeRobot datasets take no task files; evaluate on a store (--tasks STORE)")

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        return {}

    def run_rollouts(self, agent, store, rollouts, max_steps, record_frames) -> list[RolloutResult]:
        from bpp.benchmarks.lerobot.replay import run_rollouts

        return run_rollouts(agent, store, rollouts, max_steps, record_frames, self.frames)

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        """The demonstration's last frame from its first camera, or a chart of its actions if it has no camera."""
        cameras = store.config.get("cameras", [])
        if cameras:
            return self.frames(store, episode, cameras[0], size, last_only=True)[0]
        from bpp.benchmarks.lerobot.replay import action_chart

        actions = store.episode(episode, ["action"])["action"].astype(np.float64)
        return action_chart(actions, title=f"episode {episode}", size=size)

    def describe_rollout(self, row: Mapping) -> str:
        return f"episode {row.get('replayed_episode', '?')}, open loop"


def stored_frames(store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None):
    """Camera `key`'s frames of a stored episode as the contract's ``frames`` gives them (all, the last, or `steps`),
    resized if another size is asked for: for benchmarks whose stores hold their camera frames."""
    sl = store.episode_slice(episode)
    if last_only:
        rows = store[key][sl.stop - 1 : sl.stop]
    elif steps is not None:
        rows = store[key].oindex[sl.start + np.asarray(steps, dtype=np.int64)]
    else:
        rows = store[key][sl]
    return resize_frames(np.asarray(rows), size)


BENCHMARK = LeRobotDatasets()
