"""LIBERO-Gen as a registered benchmark, through the command line: generation (resumable, failures not stored,
frames rendered from stored states), every method's training on the store, evaluation by LIBERO's predicates, and
stores exported in the layout of LIBERO's released dataset files and imported back (LIBERO's own reading code reads an
export, a demonstration replays from its file alone, and an import gives the observations a rollout receives). Needs
the `libero` extra, which `make test` installs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bpp.benchmarks.libero import dataset
from bpp.benchmarks.libero.benchmark import BENCHMARK, _render
from bpp.benchmarks.libero.demonstrator import DemoConfig
from bpp.benchmarks.libero.export import CAMERA_NAMES, EXTRA_ATTRS, LIBERO_ATTRS, LIBERO_DATASETS, LIBERO_TAG
from bpp.benchmarks.libero.sim import delta_actions
from bpp.benchmarks.libero.suites import combination
from bpp.cli import main
from bpp.core.registry import open_store
from bpp.data.integrity import StoreError
from bpp.data.store import EpisodeStore
from bpp.evaluation.evaluate import resolve_tasks

pytestmark = pytest.mark.libero


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Task 0: two demonstrations, with agent-view and wrist frames at 32 px (a frame costs about 0.1 s on a CPU:
    every test of a store with frames shares this one)."""
    out = tmp_path_factory.mktemp("libero") / "train.zarr"
    flags = ["--task-indices", "0", "--demos-per-task", "2", "--cameras", "agentview", "eye_in_hand"]
    main(["libero", "generate", "--preset", "debug", "--out", str(out), "--workers", "1", "--image-size", "32", *flags])
    return open_store(out)


def test_generation_stores_only_demonstrations_that_libero_accepts(store):
    assert store.benchmark == "libero_gen" and store.num_tasks == 1 and store.num_episodes == 2
    task = store.tasks[0]
    assert task["id"] == "train-000-s1-bpr-pl" and task["instruction"] == combination().train[0].instruction
    assert "(:goal" in task["info"]["problem"]  # the task's BDDL travels with the store
    report = store.attrs["generation"]
    assert report["stored"] == 2 and report["successes"]["place PL"] == 2 and report["without_demonstrations"] == []
    assert {"action", "proprio", "object_state", "sim_state", "agentview"} <= set(store.keys)
    assert store.array("action").shape[1] == 7 and np.abs(store.array("action")).max() <= 1.0
    assert store.column(dataset.GOAL_KEY).shape == (2, 32, 32, 3)
    # action_abs: the controller's position goal, which gives back the action from where the gripper was
    eef = store.array("proprio")[:, dataset.PROPRIO_LAYOUT["eef_pos"]]
    np.testing.assert_allclose(delta_actions(store.array("action_abs"), eef), store.array("action"), atol=1e-4)
    assert not np.allclose(store.array("action_abs")[:, :3], eef)  # the gripper is told to move
    assert not list(store.path.parent.glob(".*journal*"))  # the journal is gone once the store is written


def _env_of(store: EpisodeStore, episode: int, folder: Path):
    from bpp.benchmarks.libero.rollouts import task_problem
    from bpp.benchmarks.libero.sim import make_env

    problem = folder / f"episode-{episode}.bddl"
    problem.write_text(task_problem(store, episode))
    return make_env(problem)


def test_every_stored_demonstration_replays_bit_for_bit_to_its_goal(store, tmp_path):
    """The actions are stored exactly as the controller received them (float64), and a demonstration starts as a
    replay does: replayed open-loop in a new env, every one passes through its stored states and reaches its goal."""
    assert store.array("action").dtype == np.float64
    for episode in range(store.num_episodes):
        env = _env_of(store, episode, tmp_path)
        try:
            states, success = dataset.replay_episode(env, store, episode)
        finally:
            env.close()
        np.testing.assert_array_equal(states[:-1], store.episode(episode, ["sim_state"])["sim_state"])
        assert success


def test_a_video_rendered_from_states_ends_without_renderer_errors(store, tmp_path):
    """The renderer's envs are closed before its display is terminated at exit: no EGL traceback on stderr."""
    import subprocess
    import sys

    out = tmp_path / "hand.gif"
    argv = ["-m", "bpp", "libero", "video", str(store.path), "--camera", "eye_in_hand", "--size", "16"]
    argv += ["--out", str(out)]
    done = subprocess.run([sys.executable, *argv], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and out.stat().st_size > 0, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "EGLError" not in done.stderr, done.stderr[-2000:]


def test_a_spawned_process_reads_the_derived_keys_of_the_benchmark(store):
    """A fresh interpreter that has imported nothing of LIBERO-Gen (a data-loader worker under the spawn start
    method) sees the store's derived key ``eef``: opened by its path through the registry, it comes from the benchmark
    contract, not from which modules the process happened to import; a pickled store carries it."""
    import multiprocessing as mp

    from spawned_reader import read_key

    expected = store.array("proprio")[:, list(dataset.EEF_FEATURES)]
    with mp.get_context("spawn").Pool(1, maxtasksperchild=1) as pool:  # a new process for each read
        for source in (str(store.path), store):
            before, keys, eef = pool.apply(read_key, (source, "eef"))
            assert not [m for m in before if m.startswith("bpp.benchmarks.libero")], before
            assert "eef" in keys and eef.shape == (store.num_steps, 9)
            np.testing.assert_array_equal(eef, expected)


def test_a_stored_step_renders_the_same_image_again(store):
    sl = store.episode_slice(1)
    states = store["sim_state"][sl][[0, 40, -1]]
    again = _render(store, 1, states, "agentview", 32)
    np.testing.assert_array_equal(again, store["agentview"][sl][[0, 40, -1]])
    assert np.abs(again[2].astype(int) - again[0]).max() > 20  # the arm moved: the frames differ
    assert BENCHMARK.frames(store, 1, "agentview", 16).shape == (sl.stop - sl.start, 16, 16, 3)
    with pytest.raises(ValueError, match="cameras agentview, eye_in_hand"):
        BENCHMARK.frames(store, 0, "image", 32)


def test_a_libero_dataset_file_imports_as_its_libero_task(tmp_path, capsys):
    """LIBERO's own files name their problem by path and keep no seed; the task is then evaluated from LIBERO's
    initial states. Bad files are refused with what is wrong."""
    import h5py

    from bpp.benchmarks.libero.sim import libero_problem, make_env

    goal = tmp_path / "goal.bddl"
    goal.write_text(libero_problem("libero_goal", "turn_on_the_stove"))
    env = make_env(goal)
    env.seed(0)
    env.reset()
    states = []
    for _ in range(3):
        states.append(env.env.sim.get_state().flatten())
        env.step(np.zeros(7))
    env.close()
    path = tmp_path / "turn_on_the_stove_demo.hdf5"
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["bddl_file_name"] = "libero/libero/bddl_files/libero_goal/turn_on_the_stove.bddl"
        data.attrs["problem_info"] = json.dumps({"language_instruction": "turn on the stove"})
        data.create_dataset("demo_0/actions", data=np.zeros((3, 7)))
        data.create_dataset("demo_0/states", data=np.stack(states))
    main(["libero", "import", str(path), "--out", str(tmp_path / "s.zarr"), "--goal-size", "0"])
    task = EpisodeStore(tmp_path / "s.zarr").tasks[0]
    assert task["id"] == "turn_on_the_stove" and task["instruction"] == "turn on the stove"
    assert task["info"]["initial_states"] == "libero_goal/turn_on_the_stove.pruned_init"
    with h5py.File(path, "a") as f:
        del f["data/demo_0/states"]
        f["data/demo_0/states"] = np.zeros((3, 10))
    with pytest.raises(SystemExit, match="states have 10 values, this task's LIBERO scene has"):
        main(["libero", "import", str(path), "--out", str(tmp_path / "t.zarr"), "--goal-size", "0"])
    with h5py.File(tmp_path / "empty.hdf5", "w"):
        pass
    with pytest.raises(SystemExit, match="not a LIBERO dataset file"):
        main(["libero", "import", str(tmp_path / "empty.hdf5"), "--out", str(tmp_path / "u.zarr")])


def test_failed_demonstrations_are_counted_and_never_stored(tmp_path):
    cfg = dataset.LiberoDataConfig(task_indices=(0,), demos_per_task=1, max_tries=2, demo=DemoConfig(max_steps=20))
    with pytest.raises(StoreError, match="no demonstration of 1 tasks succeeded"):
        dataset.generate(cfg, tmp_path / "s.zarr", workers=1, progress=False)  # 20 steps cannot move a bowl
    assert not (tmp_path / "s.zarr").exists()


def test_a_killed_generation_resumes_from_its_finished_tasks(tmp_path, monkeypatch):
    cfg = dataset.LiberoDataConfig(task_indices=(0, 1), demos_per_task=1, goal_size=0)
    real, calls = dataset._task_job, []

    def killed_on_the_second(job):
        calls.append(job[0])
        if job[0] == 1:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(dataset, "_task_job", killed_on_the_second)
    with pytest.raises(KeyboardInterrupt):
        dataset.generate(cfg, tmp_path / "s.zarr", workers=1, progress=False)
    assert not (tmp_path / "s.zarr").exists() and (tmp_path / ".s.zarr.journal" / "task-0000.npz").is_file()
    monkeypatch.setattr(dataset, "_task_job", lambda job: (calls.append(job[0]), real(job))[1])
    store = dataset.generate(cfg, tmp_path / "s.zarr", workers=1, progress=False)
    assert calls == [0, 1, 1]  # task 0 was not demonstrated again
    assert [t["id"] for t in store.tasks][0] == "train-000-s1-bpr-pl" and store.num_tasks == 2
    with pytest.raises(StoreError, match="already exists"):
        dataset.generate(cfg, tmp_path / "s.zarr", workers=1, progress=False)


def test_a_second_generation_into_the_same_store_is_refused_before_it_touches_the_journal(tmp_path):
    from bpp.data.destination import destination_lock

    cfg = dataset.LiberoDataConfig(task_indices=(0,), demos_per_task=1)
    journal = tmp_path / ".s.zarr.journal"
    journal.mkdir()
    (journal / "config.json").write_text("{}")  # another configuration's journal: discarded if the lock were not held
    with destination_lock(journal), pytest.raises(StoreError, match="being written by another writer"):
        dataset.generate(cfg, tmp_path / "s.zarr", workers=1, progress=False)
    assert (journal / "config.json").read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".s.zarr.journal"]  # and the lock released


@pytest.mark.parametrize(
    ("method", "obs"),
    [
        ("bpp", "state"),
        ("goal_image", "state"),
        ("language", "state"),
        ("icrt", "state"),
        ("bpp", "state-eef"),
        ("bpp", "state-abs"),
        ("bpp", "image"),
    ],
)
def test_every_method_trains_on_a_store_and_is_evaluated_by_libero(store, tmp_path, method, obs, capsys, recwarn):
    run = tmp_path / "run"
    flags = ["--preset", "debug", "--obs", obs, "--steps=2"]
    if obs == "image":  # the stored camera only, at its stored size: a wrist camera would be rendered from the
        flags += ["--model.obs.image-keys", "agentview", "--model.obs.image-size", "32"]  # states, 0.15 s a frame
    main(["train", "--method", method, "--data", str(store.path), "--out", str(run), *flags])
    seen = json.loads((run / "config.json").read_text())["model_config"]["obs"]
    assert seen["proprio_keys"] == (["eef"] if obs == "state-eef" else ["proprio"])  # eef: derived from the stored
    assert seen["image_keys"] == (["agentview"] if obs == "image" else [])
    out = tmp_path / "eval"
    flags = ["--tasks", "train", "--rollouts", "1", "--max-steps", "12", "--workers", "1", "--videos", "1"]
    main(["eval", str(run), *flags, "--out", str(out)])
    results = json.loads((out / "results.json").read_text())
    (row,) = results["rollouts"]
    assert row["score"] in (0.0, 1.0) and row["steps"] == 12  # an untrained policy does not succeed in 12 steps
    assert row["lifted"] in (0.0, 1.0) and row["lifted_other"] in (0.0, 1.0)
    assert "init_seed" in row and (out / "grid.png").is_file()
    assert list(out.glob("rollout_*.mp4")), (  # the message is built only on failure
        f"no MP4 in {sorted(p.name for p in out.iterdir())}; {[str(w.message) for w in recwarn]}"
    )


def test_bad_input_is_refused_with_a_clear_message(store, debug_store, tmp_path, capsys):
    with pytest.raises(SystemExit, match="task_indices \\[500\\] out of range"):
        main(["libero", "generate", "--out", str(tmp_path / "x.zarr"), "--task-indices", "500"])
    for command in (["video", str(debug_store.path), "--out", str(tmp_path / "v.gif")],
                    ["export", str(debug_store.path), "--out", str(tmp_path / "hdf5")]):  # fmt: skip
        with pytest.raises(SystemExit, match="is a drawanything store, not libero_gen"):
            main(["libero", *command])
    libero_checkpoint = SimpleNamespace(benchmark="libero_gen")  # all that choosing its tasks reads
    with pytest.raises(ValueError, match="holds drawanything tasks; the checkpoint was trained on libero_gen"):
        resolve_tasks(str(debug_store.path), libero_checkpoint)
    with pytest.raises(ValueError, match="'held_out': not a task set of libero_gen \\(train, held-out, "):
        resolve_tasks("held_out", libero_checkpoint)
    with pytest.raises(ValueError, match="LIBERO-Gen has no task set 'nope'; named sets: held-out, "):
        BENCHMARK.task_set("nope", tmp_path)
    with pytest.raises(SystemExit):
        main(["libero", "tasks", "--suite", "chainz"])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())  # tyro wraps its message in a box
    assert (
        "suite must be one of combination, chain, chain_no_second_step, chain_candidates, libero_spatial, libero_goal, "
        "got 'chainz'" in err
    )
    assert not (tmp_path / "x.zarr").exists()


class _Recorder:
    """An agent that records what it observes and holds the robot still."""

    def __init__(self):
        from bpp.data.spec import DataSpec

        self.data_spec = DataSpec(lowdim_keys=("proprio", "object_state"))
        self.obs_keys = ("proprio", "object_state")
        self.seen = []

    def act_batch(self, obs):
        self.seen.append({k: v.copy() for k, v in obs.items()})
        return np.zeros((len(obs["proprio"]), 7))


def test_libero_own_tasks_are_evaluated_from_libero_own_initial_states(tmp_path):
    from bpp.benchmarks.libero.demonstrator import SETTLE_STEPS
    from bpp.benchmarks.libero.rollouts import run_rollouts
    from bpp.benchmarks.libero.sim import initial_states, make_env, problems_folder

    cfg = dataset.LiberoDataConfig(suite="libero_spatial", task_indices=(1,), demos_per_task=1, goal_size=0)
    store = dataset.generate(cfg, tmp_path / "spatial.zarr", workers=1, progress=False)
    task = store.tasks[0]
    name = "pick_up_the_black_bowl_from_table_center_and_place_it_on_the_plate"
    assert task["info"]["initial_states"] == f"libero_spatial/{name}.pruned_init"
    assert task["info"]["problem"] == (problems_folder() / "libero_spatial" / f"{name}.bddl").read_text()  # verbatim
    agent = _Recorder()
    (result,) = run_rollouts(agent, store, [{"target_episode": 0, "init_seed": 53}], max_steps=3)
    assert result.steps == 3 and result.score == 0.0
    env = make_env(problems_folder() / "libero_spatial" / f"{name}.bddl")  # LIBERO's state 53 % 50 = 3, settled
    try:
        env.reset()
        obs = env.set_init_state(initial_states(f"libero_spatial/{name}.pruned_init")[3])
        for _ in range(SETTLE_STEPS):
            obs, *_ = env.step(np.zeros(7))
    finally:
        env.close()
    np.testing.assert_allclose(agent.seen[0]["object_state"][0], obs["object-state"], atol=1e-5)


@pytest.mark.parametrize("caller", ["command", "library"])
def test_a_terminated_generation_stops_its_workers(caller, tmp_path):
    """`kill` (SIGTERM) of `bpp libero generate` ends it in one line, status 143, with its workers stopped; a library
    caller killed by SIGTERM's default takes its workers with it too. Finished tasks stay in the journal."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "s.zarr"
    if caller == "command":
        argv = ["-m", "bpp", "libero", "generate", "--task-indices", "0", "1", "--demos-per-task", "1"]
        argv += ["--goal-size", "0", "--workers", "2", "--out", str(out)]
    else:
        argv = ["-c", "from bpp.benchmarks.libero.dataset import LiberoDataConfig, generate\n"
                f"generate(LiberoDataConfig(task_indices=(0, 1), demos_per_task=1, goal_size=0), {str(out)!r},"
                " workers=2, progress=False)\n"]  # fmt: skip
    main_process = subprocess.Popen([sys.executable, *argv], stderr=subprocess.PIPE, text=True)
    journal = tmp_path / ".s.zarr.journal"
    children: list[int] = []
    deadline = time.time() + 120
    while len(children) < 2 and time.time() < deadline and main_process.poll() is None:
        time.sleep(0.5)
        found = subprocess.run(["pgrep", "-P", str(main_process.pid)], capture_output=True, text=True).stdout
        children = [int(pid) for pid in found.split()]
    assert journal.is_dir() and len(children) >= 2  # the workers are demonstrating
    main_process.send_signal(signal.SIGTERM)
    _, err = main_process.communicate(timeout=60)
    if caller == "command":
        assert main_process.returncode == 143 and "Traceback" not in err, err[-2000:]
        assert err.rstrip().splitlines()[-1] == "bpp libero generate: interrupted by SIGTERM", err[-500:]
    else:
        assert main_process.returncode == -signal.SIGTERM
    time.sleep(2)
    alive = [pid for pid in children if _running(pid)]
    assert not alive, f"workers {alive} outlived the terminated generation"
    assert not out.exists()
    assert not [p for p in journal.iterdir() if p.name.startswith(".")]  # nothing half-written


def _running(pid: int) -> bool:
    """Whether process `pid` runs (an ended one may stay a zombie until the system reaps it)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# ------------------------------------------------------------ exported in LIBERO's layout, imported back


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


def test_the_score_users_read_says_a_chain_s_steps_must_come_in_order():
    said = " ".join(BENCHMARK.metric.description.split())
    assert "Chain task's two steps must be done in their order" in said
    assert "final_goal" in said and "first_step" in said


def test_where_a_chain_score_is_read_it_says_the_steps_count_in_their_order():
    label, _ = BENCHMARK._task_sets["chain-held-out"]
    assert label.endswith("(success: both steps, in their order)")
    assert "two steps must be done in their order" in BENCHMARK.metric.description  # the results.md's score line
