"""LIBERO-Gen as a registered benchmark, through the command line: generation (resumable, failures not stored,
frames rendered from stored states), every method's training on the store, and evaluation by LIBERO's
predicates. Needs the `libero` extra, which `make test` installs."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bpp.benchmarks.libero import dataset
from bpp.benchmarks.libero.benchmark import BENCHMARK, _render
from bpp.benchmarks.libero.demonstrator import DemoConfig
from bpp.benchmarks.libero.suites import combination
from bpp.cli import main
from bpp.data.store import EpisodeStore, StoreError
from bpp.evaluation.evaluate import resolve_tasks

pytestmark = pytest.mark.libero


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Task 0: two demonstrations, with agent-view frames at 32 px."""
    out = tmp_path_factory.mktemp("libero") / "train.zarr"
    flags = ["--task-indices", "0", "--demos-per-task", "2", "--cameras", "agentview"]
    main(["libero", "generate", "--preset", "debug", "--out", str(out), "--workers", "1", "--image-size", "32", *flags])
    return EpisodeStore(out)


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
    method) sees the store's derived key ``eef``: it comes from the benchmark contract through the registry, not from
    which modules the process happened to import. Whether given the path or a pickled store."""
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
    from bpp.data.store import destination_lock

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
        ("bpp", "image"),
    ],
)
def test_every_method_trains_on_a_store_and_is_evaluated_by_libero(store, tmp_path, method, obs, capsys):
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
    assert "init_seed" in row and (out / "grid.png").is_file() and list(out.glob("rollout_*.mp4"))


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
