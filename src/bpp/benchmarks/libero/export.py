"""Export a LIBERO-Gen store in the layout of LIBERO's released dataset files, one file per task.

    bpp libero export data/libero/combination-train.zarr --out exports/combination

Each task becomes ``<task id>_demo.hdf5`` beside its ``<task id>.bddl``, the way LIBERO ships its datasets (an id
that is not a safe file name, :func:`bpp.utils.file_stem`, as a slug of it and a hash). The file has the keys, dtypes
and shapes of LIBERO's released files (``data.attrs["tag"] == "libero-v1"``, written by LIBERO's
``scripts/create_dataset.py``; :data:`LIBERO_ATTRS` and :data:`LIBERO_DATASETS` list them), so LIBERO's and
robomimic's loaders and the usual LIBERO-to-LeRobot converters read it unchanged:

- ``data`` attributes: ``env_name`` (LIBERO's env class), ``problem_info`` (JSON: ``problem_name``, the key of LIBERO's
  ``TASK_MAPPING``; ``domain_name``; ``language_instruction``), ``env_args`` (JSON: ``type``, ``env_name``,
  ``problem_name``, ``bddl_file`` and the env's ``env_kwargs``, controller configuration included),
  ``bddl_file_name``, ``macros_image_convention``, ``num_demos``, ``total`` and ``tag``.
- per ``demo_<i>``: attributes ``num_samples``, ``model_file`` (the scene's MuJoCo XML) and ``init_state`` (the first
  state); datasets ``actions`` (T, 7), ``states`` (T, S) (the flattened simulator state before each action),
  ``robot_states`` (T, 9: gripper joints, hand position, hand quaternion x y z w), ``rewards`` and ``dones`` (1 at the
  last step); ``obs``: ``joint_states`` (7), ``gripper_states`` (2), ``ee_pos`` (3), ``ee_ori`` (3, axis-angle),
  ``ee_states`` (6, both), and ``agentview_rgb`` / ``eye_in_hand_rgb`` (uint8, rotated by 180 degrees from upright
  as LIBERO's files hold them; bpp stores them upright).

Where the store differs from LIBERO's files:

- Camera frames are written only if the store has them (``--cameras`` at generation); LIBERO's files always have both.
- ``obs`` at step t is what the policy observed when it chose action t, in the state ``states[t]``. LIBERO's
  ``create_dataset.py`` records each observation after executing the action of its row, one step later than the
  row's state, and drops the first 5 steps.
- The images have the store's size (LIBERO's: 128 x 128), which ``env_args`` states.
- Our own information is kept where LIBERO's readers do not look: ``data.attrs["bpp_task"]`` (the task's id and
  information, JSON), ``data.attrs["bddl_file_content"]`` (the problem's text: LIBERO's ``create_dataset.py`` writes
  it too, its released files do not have it), ``demo_<i>.attrs["bpp_seed"]`` (the seed of the demonstration's reset)
  and, for a store generated with action noise, ``demo_<i>/bpp_actions``: the clean actions to learn, while
  ``actions`` are the executed ones that reproduce the states.

``model_file`` is the MJCF robosuite built the demonstration's scene from, with the fixtures (table, cabinet, stove)
where its reset put them, to full precision. An env of the problem, reset, then made with LIBERO's
``env.reset_from_xml_string(model_file)`` and started with :func:`bpp.benchmarks.libero.sim.seat` from ``states[0]``,
reproduces every state of the demonstration bit for bit by executing ``actions``.
"""

from __future__ import annotations

import json
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from bpp.benchmarks.libero.dataset import PROPRIO_LAYOUT, episode_fixtures
from bpp.benchmarks.libero.sim import CAMERAS, make_env, reset_scene
from bpp.data.store import EpisodeStore
from bpp.errors import UserError, require_extra
from bpp.utils import atomic_path, file_stem, write_text_atomic

LIBERO_TAG = "libero-v1"
"""``data.attrs["tag"]`` of LIBERO's released dataset files, the layout these files have."""
LIBERO_ATTRS = {
    "data": (
        "bddl_file_name",
        "env_args",
        "env_name",
        "macros_image_convention",
        "num_demos",
        "problem_info",
        "tag",
        "total",
    ),
    "data/demo_<i>": ("init_state", "model_file", "num_samples"),
}
"""The attributes of LIBERO's released dataset files (``libero_goal/*_demo.hdf5``, tag ``libero-v1``)."""
LIBERO_DATASETS: dict[str, tuple[str, tuple[int | None, ...]]] = {
    "actions": ("float64", (7,)),
    "dones": ("uint8", ()),
    "obs/agentview_rgb": ("uint8", (None, None, 3)),
    "obs/ee_ori": ("float64", (3,)),
    "obs/ee_pos": ("float64", (3,)),
    "obs/ee_states": ("float64", (6,)),
    "obs/eye_in_hand_rgb": ("uint8", (None, None, 3)),
    "obs/gripper_states": ("float64", (2,)),
    "obs/joint_states": ("float64", (7,)),
    "rewards": ("uint8", ()),
    "robot_states": ("float64", (9,)),
    "states": ("float64", (None,)),
}
"""Each demonstration's datasets in LIBERO's released files: (dtype, shape after the step axis; None: any size)."""
EXTRA_ATTRS = {"data": ("bddl_file_content", "bpp_task"), "data/demo_<i>": ("bpp_seed",)}
"""The attributes these files add to LIBERO's (see the module's docstring)."""
CAMERA_NAMES = {"agentview": "agentview_rgb", "eye_in_hand": "eye_in_hand_rgb"}
"""Store camera keys -> LIBERO's dataset observation keys."""


def export_store(store: EpisodeStore, out: Path, overwrite: bool = False) -> list[Path]:
    """Write one HDF5 file (and its BDDL) per task of `store` into the folder `out`; returns the HDF5 paths. Each
    task's LIBERO env is made (physics only) to write every demonstration's scene."""
    h5py = require_extra("h5py", "libero")

    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise UserError(f"{out} exists and is not empty; pass --overwrite to write into it")
    for task in store.tasks:  # every task is checked before anything is written
        if not task["info"].get("problem"):
            raise UserError(f"{store.path}: task {task['id']!r} has no BDDL problem; generate the store again")
    out.mkdir(parents=True, exist_ok=True)
    by_task = store.task_episodes()
    written = []
    with tempfile.TemporaryDirectory(prefix="libero-export-") as folder:
        for index, task in enumerate(store.tasks):
            name = file_stem(task["id"])  # the id itself unless it is not a safe file name (bpp_task keeps it)
            problem = task["info"]["problem"]
            write_text_atomic(out / f"{name}.bddl", problem)
            problem_path = Path(folder) / f"task-{index}.bddl"
            problem_path.write_text(problem)
            env = make_env(problem_path)
            try:
                path = out / f"{name}_demo.hdf5"
                with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:  # complete or absent (a full disk, Ctrl-C)
                    _write_task(f, store, task, [int(e) for e in by_task[index]], env, libero_file_name(task, name))
            finally:
                env.close()
            written.append(path)
    return written


def libero_file_name(task: dict, name: str) -> str:
    """``bddl_file_name`` of a task's file: for one of LIBERO's own problems, its path as LIBERO's files name it
    (which LIBERO's tools and ``bpp libero import`` recognise); else the problem's file beside the export."""
    initial = task["info"].get("initial_states")
    if initial:  # "<suite>/<stem>.pruned_init": the task is LIBERO's problem <stem> of <suite>
        suite, stem = initial.removesuffix(".pruned_init").split("/")
        return f"libero/libero/bddl_files/{suite}/{stem}.bddl"
    return f"{name}.bddl"


def _write_task(f, store: EpisodeStore, task: dict, episodes: list[int], env, bddl_file_name: str) -> None:
    """Write `task`'s `episodes` into the open HDF5 file `f`; `env` is the task's LIBERO env."""
    # robosuite: the libero extra
    import robosuite.macros

    cameras = [key for key in CAMERA_NAMES if key in store.keys]
    actions = "executed_action" if "executed_action" in store.keys else "action"  # those that reproduce the states
    keys = ["sim_state", "proprio", "action", *cameras] + ([actions] if actions != "action" else [])
    size = int(store[cameras[0]].shape[1]) if cameras else 128
    env_name = type(env.env).__name__
    problem_name = env.problem_name
    data = f.create_group("data")
    data.attrs["env_name"] = env_name
    data.attrs["problem_info"] = json.dumps(
        {"problem_name": problem_name, "domain_name": "robosuite", "language_instruction": task["instruction"]}
    )
    data.attrs["env_args"] = json.dumps(
        {
            "type": 1,  # robomimic's EnvType.ROBOSUITE_TYPE
            "env_name": env_name,
            "problem_name": problem_name,
            "bddl_file": bddl_file_name,
            "env_kwargs": env_kwargs(env, bddl_file_name, size),
        }
    )
    data.attrs["bddl_file_name"] = bddl_file_name
    data.attrs["bddl_file_content"] = task["info"]["problem"]
    data.attrs["macros_image_convention"] = robosuite.macros.IMAGE_CONVENTION
    data.attrs["tag"] = LIBERO_TAG
    data.attrs["bpp_task"] = json.dumps(
        {"id": task["id"], "info": {k: v for k, v in task["info"].items() if k != "problem"}}
    )
    total = 0
    for i, episode in enumerate(episodes):
        steps = store.episode(episode, keys)
        n = len(steps["sim_state"])
        demo = data.create_group(f"demo_{i}")
        demo.attrs["num_samples"] = n
        demo.attrs["model_file"] = scene_xml(env, int(store.column("seed")[episode]), episode_fixtures(store, episode))
        demo.attrs["init_state"] = steps["sim_state"][0]
        demo.attrs["bpp_seed"] = int(store.column("seed")[episode])
        demo.create_dataset("actions", data=steps[actions].astype(np.float64))
        if actions != "action":
            demo.create_dataset("bpp_actions", data=steps["action"].astype(np.float64))
        demo.create_dataset("states", data=steps["sim_state"].astype(np.float64))
        last = np.zeros(n, dtype=np.uint8)
        last[-1] = 1
        demo.create_dataset("rewards", data=last)
        demo.create_dataset("dones", data=last)
        obs = libero_observations(steps["proprio"])
        demo.create_dataset("robot_states", data=obs.pop("robot_states"))
        group = demo.create_group("obs")
        for key, values in obs.items():
            group.create_dataset(key, data=values)
        for key in cameras:
            frames = np.ascontiguousarray(steps[key][:, ::-1, ::-1])
            group.create_dataset(CAMERA_NAMES[key], data=frames, compression="gzip", compression_opts=4)
        total += n
    data.attrs["num_demos"] = len(episodes)
    data.attrs["total"] = total


def env_kwargs(env, bddl_file_name: str, size: int) -> dict:
    """The ``env_kwargs`` of ``env_args`` as LIBERO's files keep them: the arguments of LIBERO's env that recorded
    the observations (robomimic makes its env from them), for `env` (made by
    :func:`~bpp.benchmarks.libero.sim.make_env`), with both cameras at `size`."""
    # robosuite: the libero extra
    from robosuite import load_controller_config

    inner = env.env
    return {
        "robots": ["Panda"],  # make_env's robot (LIBERO's env mounts it: inner.robots name it MountedPanda)
        "controller_configs": load_controller_config(default_controller="OSC_POSE"),  # make_env's controller
        "bddl_file_name": bddl_file_name,
        "has_renderer": False,
        "has_offscreen_renderer": True,
        "ignore_done": True,
        "use_camera_obs": True,
        "camera_depths": False,
        "camera_names": [CAMERAS["eye_in_hand"], CAMERAS["agentview"]],  # LIBERO's order
        "reward_shaping": True,
        "control_freq": inner.control_freq,
        "camera_heights": size,
        "camera_widths": size,
        "camera_segmentations": None,
    }


def libero_observations(proprio: np.ndarray) -> dict[str, np.ndarray]:
    """LIBERO's observation datasets (and ``robot_states``), float64, from stored 39-D proprioception
    (:data:`~bpp.benchmarks.libero.dataset.PROPRIO_LAYOUT`): the orientation as LIBERO's ``create_dataset.py``
    computes it, robosuite's ``quat2axisangle`` of the hand's quaternion."""
    # robosuite: the libero extra
    from robosuite.utils.transform_utils import quat2axisangle

    proprio = np.asarray(proprio, dtype=np.float64)

    def part(name: str) -> np.ndarray:
        return proprio[:, list(PROPRIO_LAYOUT[name])]

    ee_pos, quat, gripper = part("eef_pos"), part("eef_quat"), part("gripper_qpos")
    ee_ori = np.stack([quat2axisangle(q.copy()) for q in quat])  # it clips w in place
    return {
        "joint_states": part("joint_pos"),
        "gripper_states": gripper,
        "ee_pos": ee_pos,
        "ee_ori": ee_ori,
        "ee_states": np.concatenate([ee_pos, ee_ori], axis=1),
        "robot_states": np.concatenate([gripper, ee_pos, quat], axis=1),  # LIBERO's get_robot_state_vector
    }


def scene_xml(env, seed: int, fixtures: tuple[list[str], np.ndarray] | None) -> str:
    """The MJCF of a demonstration's scene, its ``model_file``: `env` reset with its `seed`, the fixtures put back
    (``fixtures``: names and poses; None for a store that did not keep them, whose scene the seed's reset only
    approximates). It is the XML robosuite compiled the scene from, with each fixture's pose written to full
    precision: LIBERO places the fixtures in the compiled model, and MuJoCo's own saved XML (what LIBERO's files
    keep) rounds every number to 6 digits, which moved them by up to 4e-7 m and the robot's armature by 3e-6, and a
    replay of the demonstration in it diverged by centimetres."""
    reset_scene(env, seed, fixtures)
    inner = env.env
    model = inner.sim.model
    root = ET.fromstring(inner.model.get_xml())
    bodies = {body.get("name"): body for body in root.iter("body")}
    for fixture in inner.fixtures_dict.values():
        index = model.body_name2id(fixture.root_body)
        body = bodies[fixture.root_body]
        body.set("pos", " ".join(repr(float(x)) for x in model.body_pos[index]))
        body.set("quat", " ".join(repr(float(x)) for x in model.body_quat[index]))
    return ET.tostring(root, encoding="unicode")
