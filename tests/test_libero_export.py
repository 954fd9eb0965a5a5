"""LIBERO-Gen stores exported in the layout of LIBERO's released dataset files and imported back: LIBERO's own reading
code reads an export, a demonstration replays from its file alone, and an import gives the observations a rollout
receives. Needs the `libero` extra, which `make test` installs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bpp.benchmarks.libero import dataset
from bpp.benchmarks.libero.export import CAMERA_NAMES, EXTRA_ATTRS, LIBERO_ATTRS, LIBERO_DATASETS, LIBERO_TAG
from bpp.cli import main
from bpp.data.store import EpisodeStore

pytestmark = pytest.mark.libero


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Task 0: two demonstrations, with agent-view and wrist frames at 32 px."""
    out = tmp_path_factory.mktemp("libero") / "train.zarr"
    flags = ["--task-indices", "0", "--demos-per-task", "2", "--cameras", "agentview", "eye_in_hand"]
    main(["libero", "generate", "--preset", "debug", "--out", str(out), "--workers", "1", "--image-size", "32", *flags])
    return EpisodeStore(out)


@pytest.fixture(scope="module")
def exported(store, tmp_path_factory) -> Path:
    """The store exported: the one task's HDF5 file (its BDDL beside it)."""
    out = tmp_path_factory.mktemp("export")
    main(["libero", "export", str(store.path), "--out", str(out)])
    (path,) = out.glob("*.hdf5")
    return path


def _datasets(h5py, group) -> dict:
    found = {}
    group.visititems(lambda name, item: found.update({name: item}) if isinstance(item, h5py.Dataset) else None)
    return found


def test_an_export_has_the_layout_of_libero_released_files(store, exported, capsys):
    """Key for key, with LIBERO's dtypes and shapes, the values taken from the store; LIBERO's own
    ``get_dataset_info`` reads it, and its ``problem_name`` is the env LIBERO's tools make."""
    import h5py
    from libero.libero.envs import TASK_MAPPING
    from libero.libero.utils.dataset_utils import get_dataset_info
    from scipy.spatial.transform import Rotation

    task = store.tasks[0]
    assert exported.name == "train-000-s1-bpr-pl_demo.hdf5"
    with h5py.File(exported) as f:
        data = f["data"]
        assert set(data.attrs) == {*LIBERO_ATTRS["data"], *EXTRA_ATTRS["data"]}
        assert sorted(data) == ["demo_0", "demo_1"]  # robomimic reads every key of data as a demonstration
        info = json.loads(data.attrs["problem_info"])
        assert info["language_instruction"] == task["instruction"] and info["domain_name"] == "robosuite"
        assert TASK_MAPPING[info["problem_name"]].__name__ == data.attrs["env_name"] == "Libero_Tabletop_Manipulation"
        args = json.loads(data.attrs["env_args"])
        assert args["type"] == 1 and args["env_name"] == data.attrs["env_name"]
        assert args["problem_name"] == info["problem_name"]
        assert args["bddl_file"] == args["env_kwargs"]["bddl_file_name"] == data.attrs["bddl_file_name"]
        assert (exported.parent / data.attrs["bddl_file_name"]).read_text() == task["info"]["problem"]
        assert args["env_kwargs"]["controller_configs"]["type"] == "OSC_POSE"
        assert args["env_kwargs"]["camera_heights"] == args["env_kwargs"]["camera_widths"] == 32
        assert data.attrs["tag"] == LIBERO_TAG and data.attrs["macros_image_convention"] == "opengl"
        assert json.loads(data.attrs["bpp_task"])["id"] == task["id"]
        assert data.attrs["num_demos"] == 2 and data.attrs["total"] == store.num_steps
        for i, name in enumerate(["demo_0", "demo_1"]):
            demo, steps = data[name], store.episode(i)
            n = len(steps["action"])
            assert set(demo.attrs) == {*LIBERO_ATTRS["data/demo_<i>"], *EXTRA_ATTRS["data/demo_<i>"]}
            assert demo.attrs["num_samples"] == n and demo.attrs["bpp_seed"] == store.column("seed")[i]
            assert demo.attrs["model_file"].startswith("<mujoco")
            found = _datasets(h5py, demo)
            assert set(found) == set(LIBERO_DATASETS)
            for key, (dtype, shape) in LIBERO_DATASETS.items():
                assert found[key].dtype == dtype and found[key].shape[0] == n, key
                assert len(found[key].shape) == 1 + len(shape), key
                assert all(want in (None, got) for want, got in zip(shape, found[key].shape[1:], strict=True)), key
            np.testing.assert_array_equal(demo["actions"][:], steps["action"])
            np.testing.assert_array_equal(demo["states"][:], steps["sim_state"])
            np.testing.assert_array_equal(demo.attrs["init_state"], steps["sim_state"][0])
            np.testing.assert_array_equal(demo["rewards"][:], np.eye(n, dtype=np.uint8)[-1])
            np.testing.assert_array_equal(demo["dones"][:], np.eye(n, dtype=np.uint8)[-1])
            proprio = steps["proprio"].astype(np.float64)
            part = {name: proprio[:, list(features)] for name, features in dataset.PROPRIO_LAYOUT.items()}
            np.testing.assert_array_equal(demo["obs/joint_states"][:], part["joint_pos"])
            np.testing.assert_array_equal(demo["obs/gripper_states"][:], part["gripper_qpos"])
            np.testing.assert_array_equal(demo["obs/ee_pos"][:], part["eef_pos"])
            robot = np.concatenate([part["gripper_qpos"], part["eef_pos"], part["eef_quat"]], axis=1)
            np.testing.assert_array_equal(demo["robot_states"][:], robot)
            ee_states = np.concatenate([demo["obs/ee_pos"][:], demo["obs/ee_ori"][:]], axis=1)
            np.testing.assert_array_equal(demo["obs/ee_states"][:], ee_states)
            turned = Rotation.from_rotvec(demo["obs/ee_ori"][:]) * Rotation.from_quat(part["eef_quat"]).inv()
            assert np.abs(turned.magnitude()).max() < 1e-5  # the hand's orientation as an axis-angle vector
            for key, libero_key in CAMERA_NAMES.items():  # rotated by 180 degrees, as LIBERO's files hold them
                np.testing.assert_array_equal(demo["obs"][libero_key][:][:, ::-1, ::-1], steps[key])
    get_dataset_info(str(exported), verbose=False)
    printed = capsys.readouterr().out
    assert f"total transitions: {store.num_steps}" in printed
    assert f"language instruction: {task['instruction']}" in printed
    assert f"episode demo_0 with {len(store.episode(0)['action'])} transitions" in printed
    assert "observation key ee_states with shape" in printed
    with pytest.raises(SystemExit, match="not empty"):
        main(["libero", "export", str(store.path), "--out", str(exported.parent)])


def test_a_demonstration_replays_from_its_exported_file_alone(exported):
    """A LIBERO env of the file's problem loads the demonstration's scene from ``model_file`` (fixtures included),
    and from ``states[0]`` its ``actions`` pass through every stored state and reach the goal."""
    import h5py

    from bpp.benchmarks.libero.sim import make_env, seat

    with h5py.File(exported) as f:
        problem = exported.parent / f["data"].attrs["bddl_file_name"]
        demo = f["data/demo_1"]
        model, states, actions = demo.attrs["model_file"], demo["states"][:], demo["actions"][:]
    env = make_env(problem)
    try:
        env.seed(12345)  # another reset: the scene comes from the file
        env.reset()
        env.env.reset_from_xml_string(model)
        seat(env, states[0])
        seen = [env.env.sim.get_state().flatten()]
        for action in actions[:-1]:
            env.step(action)
            seen.append(env.env.sim.get_state().flatten())
        env.step(actions[-1])
        np.testing.assert_array_equal(np.stack(seen), states)
        assert env.env._check_success()
    finally:
        env.close()


def test_exported_files_import_back_with_the_observations_a_rollout_sees(store, exported, tmp_path, capsys):
    """Import replays each demonstration in the scene of its ``model_file``, so the observations, fixtures and goal
    frames are those the demonstration saw, bit for bit. A file whose scene does not reproduce its states (here: the
    scene as MuJoCo saves it, rounded to 6 digits, as LIBERO's own files keep it, naming its assets in another
    machine's folders) starts each step from the stored state and stays close to what a rollout observes."""
    import h5py
    import robosuite
    from libero.libero import get_libero_path

    from bpp.benchmarks.libero.sim import make_env

    main(["libero", "import", str(exported), "--out", str(tmp_path / "back.zarr"), "--goal-size", "32"])
    back = EpisodeStore(tmp_path / "back.zarr")
    assert back.benchmark == "libero_gen" and back.num_episodes == 2
    assert [{k: t[k] for k in ("id", "instruction")} for t in back.tasks] == [
        {k: t[k] for k in ("id", "instruction")} for t in store.tasks
    ]
    info = {k: v for k, v in back.tasks[0]["info"].items() if k != "source"}
    assert info == store.tasks[0]["info"]
    np.testing.assert_array_equal(back.column("seed"), store.column("seed"))
    for key in ("action", "sim_state", "proprio", "object_state"):
        np.testing.assert_array_equal(back.array(key), store.array(key), err_msg=key)
    np.testing.assert_array_equal(back.column(dataset.FIXTURE_KEY), store.column(dataset.FIXTURE_KEY))
    np.testing.assert_array_equal(back.column(dataset.GOAL_KEY), store.column(dataset.GOAL_KEY))

    foreign = tmp_path / exported.name
    installed = Path(robosuite.__file__).parent
    shutil.copy(exported, foreign)
    with h5py.File(foreign) as f:
        problem = exported.parent / f["data"].attrs["bddl_file_name"]
    env = make_env(problem)
    try:
        with h5py.File(foreign, "a") as f:
            del f["data/demo_1"]
            demo = f["data/demo_0"]
            env.reset()
            env.env.reset_from_xml_string(demo.attrs["model_file"])
            saved = env.env.sim.model.get_xml().replace(str(installed), "/elsewhere/robosuite")
            saved = saved.replace(str(get_libero_path("assets")), "/elsewhere/LIBERO/libero/libero/assets")
            assert str(installed.parent) not in saved  # no file where this installation has it
            demo.attrs["model_file"] = saved
    finally:
        env.close()
    main(["libero", "import", str(foreign), "--out", str(tmp_path / "foreign.zarr"), "--goal-size", "0"])
    near = EpisodeStore(tmp_path / "foreign.zarr").episode(0)
    steps = store.episode(0)
    assert not np.array_equal(near["proprio"], steps["proprio"])  # this scene does not reproduce the states
    moved = np.abs(near["proprio"] - steps["proprio"])
    angles = [i for part in ("joint_pos", "eef_pos", "eef_quat") for i in dataset.PROPRIO_LAYOUT[part]]
    assert moved[:, angles].max() < 1e-5 and moved.max() < 5e-3, moved.max(0)
    assert np.abs(near["object_state"] - steps["object_state"]).max() < 1e-2
