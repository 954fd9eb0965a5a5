"""iPhUMI recordings as a benchmark (the contract of :mod:`bpp.core.contract`): stores made by
``bpp iphumi process`` from phone recordings, their observation presets, and open-loop evaluation on held-out
episodes (there is no simulator of a person's table), as for every benchmark of recorded demonstrations
(:class:`bpp.recorded.benchmark.RecordedDemonstrations`).

Nothing here imports OpenCV: only processing recordings needs the ``iphumi`` extra.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from bpp.benchmarks.iphumi.pipeline import BENCHMARK as NAME
from bpp.data.spec import ObservationPreset
from bpp.errors import UserError
from bpp.recorded.benchmark import RecordedDemonstrations

IMAGE_SIZE = 96
"""The presets' camera size (``bpp iphumi process``'s default: frames are used as stored)."""

OBSERVATIONS: Mapping[str, ObservationPreset] = {
    "wrist": ObservationPreset(
        proprio_keys=("pose", "width"),
        image_keys=("rgb",),
        image_size=IMAGE_SIZE,
        goal_camera="rgb",
        description="the paper's real setting: the gripper's pose (relative to the episode's start) and width, and "
        "the phone's main camera at 96x96",
    ),
    "state": ObservationPreset(
        proprio_keys=("pose", "width"),
        goal_camera="rgb",
        description="the gripper's pose and width alone; for CPUs",
    ),
    "bimanual": ObservationPreset(
        proprio_keys=("pose", "width", "arm1_pose", "arm1_width"),
        image_keys=("rgb", "arm1_rgb"),
        image_size=IMAGE_SIZE,
        goal_camera="rgb",
        description="both grippers' poses (in the right one's starting frame) and widths, and both main cameras",
    ),
}


@dataclass(frozen=True)
class NoGeneration:
    """iPhUMI stores are processed from recordings, not generated: this configuration has nothing to set."""


class IPhUMIRecordings(RecordedDemonstrations):
    """Demonstrations recorded with iPhUMI phones: train on them, evaluate open loop on held-out episodes, prompt a
    served policy with one recording."""

    name = NAME
    command = "iphumi"
    command_table = "bpp.benchmarks.iphumi.commands:COMMANDS"
    description = (
        "iPhUMI phone recordings: process an export into a store (bpp iphumi process), prompt a served policy with "
        "one recording (bpp iphumi prompt); evaluated open loop by the action error on held-out episodes"
    )
    data_config = NoGeneration
    data_presets = {"debug": NoGeneration()}
    default_data_dir = Path("data/iphumi")
    observations = OBSERVATIONS

    def default_observation(self, size: str) -> str:
        return "state" if size == "debug" else "wrist"

    def generate(self, cfg, out: Path, *, workers: int = 0, overwrite: bool = False, progress: bool = True):
        raise UserError(
            "iPhUMI stores are processed from recordings, not generated: bpp iphumi process EXPORT_DIR --out STORE "
            "(bpp iphumi synth DIR writes synthetic recordings to try it)"
        )

    def task_set(self, name: str, data_dir: Path, workers: int = 0):
        raise UserError(
            f"iPhUMI stores have no named task set {name!r}; evaluate on the held-out store bpp iphumi process wrote "
            "(bpp eval RUN --tasks STORE-heldout.zarr) or on the training tasks (--tasks train)"
        )

    def task_set_from_files(self, files, data_dir: Path, workers: int = 0):
        raise UserError("iPhUMI stores take no task files; evaluate on a store (--tasks STORE)")


BENCHMARK = IPhUMIRecordings()
