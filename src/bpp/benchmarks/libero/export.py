"""Export a LIBERO-Gen store in LIBERO's own dataset layout (robomimic-style HDF5), one file per task.

    bpp libero export data/libero/combination-train.zarr --out exports/combination

Each task becomes ``<task id>_demo.hdf5`` beside its ``<task id>.bddl``, the way LIBERO ships its datasets (an id
that is not a safe file name, :func:`bpp.utils.file_stem`, as a slug of it and a hash):
``data`` holds the problem (``bddl_file_content``, ``problem_info`` with the instruction, ``env_args``) and one group
``demo_<i>`` per demonstration with ``actions`` (T, 7), the flattened simulator ``states`` (T, 92), ``robot_states``,
``rewards`` and ``dones`` (1 at the last step), and ``obs``: ``joint_states``, ``ee_pos``, ``ee_quat``,
``gripper_states`` (sliced from LIBERO's 39-D proprioception) and ``object_state``, plus ``agentview_rgb`` /
``eye_in_hand_rgb`` if the store has camera frames. Images are written as LIBERO's files keep them: rotated by 180
degrees from upright (bpp stores them upright).

The demonstration's initial placement comes from LIBERO's sampler seeded with ``seed`` (kept per demonstration): to
replay a demonstration, make the env from the BDDL file, ``env.seed(seed); env.reset()``, then set each state.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.dataset import PROPRIO_LAYOUT
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.utils import atomic_path, file_stem, write_text_atomic

PROPRIO_PARTS = {
    "joint_states": "joint_pos",
    "ee_pos": "eef_pos",
    "ee_quat": "eef_quat",
    "gripper_states": "gripper_qpos",
}
"""LIBERO's dataset observation keys -> the parts of the stored proprioception they hold
(:data:`~bpp.benchmarks.libero.dataset.PROPRIO_LAYOUT`)."""
CAMERA_NAMES = {"agentview": "agentview_rgb", "eye_in_hand": "eye_in_hand_rgb"}


def export_store(store: EpisodeStore, out: Path, overwrite: bool = False) -> list[Path]:
    """Write one HDF5 file (and its BDDL) per task of `store` into the folder `out`; returns the HDF5 paths."""
    from bpp.errors import require_extra

    h5py = require_extra("h5py", "libero")

    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise UserError(f"{out} exists and is not empty; pass --overwrite to write into it")
    out.mkdir(parents=True, exist_ok=True)
    by_task = store.task_episodes()
    cameras = [key for key in CAMERA_NAMES if key in store.keys]
    written = []
    for index, task in enumerate(store.tasks):
        problem = task["info"].get("problem")
        if not problem:
            raise UserError(f"{store.path}: task {task['id']!r} has no BDDL problem; generate the store again")
        name = file_stem(task["id"])  # the id itself unless it is not a safe file name (problem_name keeps it)
        write_text_atomic(out / f"{name}.bddl", problem)
        path = out / f"{name}_demo.hdf5"
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:  # complete or absent (a full disk, Ctrl-C)
            data = f.create_group("data")
            data.attrs["bddl_file_name"] = f"{name}.bddl"
            data.attrs["bddl_file_content"] = problem
            data.attrs["problem_info"] = json.dumps(
                {"language_instruction": task["instruction"], "problem_name": task["id"], "domain_name": "robosuite"}
            )
            data.attrs["env_args"] = json.dumps(
                {"type": 1, "env_name": "libero_gen", "env_kwargs": {"controller": "OSC_POSE", "control_freq": 20}}
            )
            data.attrs["macros_image_convention"] = "opengl"
            total = 0
            for i, episode in enumerate(by_task[index]):
                steps = store.episode(int(episode), ["action", "proprio", "object_state", "sim_state", *cameras])
                n = len(steps["action"])
                demo = data.create_group(f"demo_{i}")
                demo.attrs["num_samples"] = n
                demo.attrs["seed"] = int(store.column("seed")[episode])
                demo.create_dataset("actions", data=steps["action"].astype(np.float64))
                demo.create_dataset("states", data=steps["sim_state"])
                demo.create_dataset("robot_states", data=steps["proprio"].astype(np.float64))
                done = np.zeros(n, dtype=np.uint8)
                done[-1] = 1
                demo.create_dataset("rewards", data=done)
                demo.create_dataset("dones", data=done)
                obs = demo.create_group("obs")
                for name, part in PROPRIO_PARTS.items():
                    features = list(PROPRIO_LAYOUT[part])
                    obs.create_dataset(name, data=steps["proprio"][:, features].astype(np.float64))
                obs.create_dataset("object_state", data=steps["object_state"].astype(np.float64))
                for key in cameras:
                    frames = np.ascontiguousarray(steps[key][:, ::-1, ::-1])
                    obs.create_dataset(CAMERA_NAMES[key], data=frames, compression="gzip", compression_opts=4)
                total += n
            data.attrs["total"] = total
            data.attrs["num_demos"] = len(by_task[index])
        written.append(path)
    return written
