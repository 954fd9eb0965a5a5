"""Imported LeRobot datasets as a benchmark (the contract of :mod:`bpp.core.contract`): their observation
presets, their stored camera frames, and open-loop evaluation on held-out episodes, since there is no simulator
(:class:`bpp.recorded.benchmark.RecordedDemonstrations`).

Stores of this benchmark come from ``bpp lerobot import``; ``bpp lerobot generate`` only says so. Nothing here
imports LeRobot's library: only the import and export commands need the ``lerobot`` extra.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from bpp.benchmarks.lerobot.importer import BENCHMARK as NAME
from bpp.core.contract import TaskSet
from bpp.data.spec import ObservationPreset
from bpp.errors import UserError
from bpp.recorded.benchmark import RecordedDemonstrations

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


class LeRobotDatasets(RecordedDemonstrations):
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
    observations = OBSERVATIONS

    def default_observation(self, size: str) -> str:
        return "robot"

    def generate(self, cfg, out: Path, *, workers: int = 0, overwrite: bool = False, progress: bool = True):
        raise UserError(
            "LeRobot datasets are imported, not generated: bpp lerobot import PATH_OR_REPO_ID --out STORE "
            "(see bpp lerobot import --help)"
        )

    # ------------------------------------------------------------ evaluation
    def task_set(self, name: str, data_dir: Path, workers: int = 0) -> TaskSet:
        raise UserError(
            f"imported LeRobot datasets have no named task set {name!r}; evaluate on the held-out store the import "
            "wrote (bpp eval RUN --tasks STORE-heldout.zarr) or on the training tasks (--tasks train)"
        )

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: int = 0) -> TaskSet:
        raise UserError("imported LeRobot datasets take no task files; evaluate on a store (--tasks STORE)")


BENCHMARK = LeRobotDatasets()
