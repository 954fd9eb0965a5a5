"""LeRobot datasets in and out: a dataset made here with LeRobot's own library imports into a store (tasks, keys,
cameras, fps, held-out episodes), trains BPP and is evaluated open loop; any store exports to a LeRobot v3 dataset
that LeRobot's loader reads back, and imports back to the same arrays. Needs LeRobot (the `lerobot` extra): `make test`
runs this file in LeRobot's environment, .venv-lerobot."""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bpp.benchmarks.lerobot.benchmark import BENCHMARK
from bpp.benchmarks.lerobot.export import _action_like, action_feature, export_store
from bpp.cli import main
from bpp.data.spec import DataSpec
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError
from bpp.recorded.replay import replayed_episode, run_rollouts
from helpers import import_optional

pytestmark = pytest.mark.lerobot

library = import_optional("bpp.benchmarks.lerobot.library", "lerobot")

TASKS = ["pick up the red cube", "push the block to the left", "open the drawer"]
EPISODES_PER_TASK, STEPS, FPS = 4, 10, 10
HEIGHT, WIDTH = 24, 32  # the video camera's frames: not square, so importing resizes them


@pytest.fixture(scope="module", autouse=True)
def home_cache(tmp_path_factory):
    """The `datasets` package's default cache (the user's home, as far as it knows): bpp must write nothing there."""
    import datasets

    before = datasets.config.HF_DATASETS_CACHE
    datasets.config.HF_DATASETS_CACHE = tmp_path_factory.mktemp("home-datasets-cache")
    yield datasets.config.HF_DATASETS_CACHE
    datasets.config.HF_DATASETS_CACHE = before


def _frame(episode: int, step: int, height: int, width: int) -> np.ndarray:
    """A smooth picture that differs between episodes and steps (what a lossy video keeps)."""
    y, x = np.mgrid[0:height, 0:width]
    base = np.array([40 + 15 * episode, 200 - 12 * step, 90 + 5 * (episode + step)])
    return np.clip(base + 3 * x[..., None] + 2 * y[..., None], 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A LeRobot v3 dataset written by LeRobot's library: 3 tasks x 4 episodes of 10 frames, a 3-D state, a 4-D
    action, a video camera (24x32) and an image camera (16x16); and the arrays it was given."""
    lib = library.dataset_library()
    root = tmp_path_factory.mktemp("lerobot") / "robot"
    features = {
        "observation.state": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
        "action": {"dtype": "float32", "shape": (4,), "names": ["x", "y", "z", "gripper"]},
        "observation.images.front": {
            "dtype": "video",
            "shape": (HEIGHT, WIDTH, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.images.wrist": {"dtype": "image", "shape": (16, 16, 3), "names": ["height", "width", "channels"]},
    }
    rng = np.random.default_rng(0)
    given = {"state": [], "action": [], "front": [], "wrist": [], "task": []}
    with library.offline_and_quiet(root):
        dataset = lib.LeRobotDataset.create(
            "test/robot", fps=FPS, features=features, root=root, robot_type="arm", video_backend="pyav"
        )
        for episode in range(len(TASKS) * EPISODES_PER_TASK):
            task = episode % len(TASKS)  # tasks interleaved, so held-out episodes are not simply the last ones
            state = rng.normal(size=(STEPS, 3)).astype(np.float32)
            action = np.concatenate([state + 0.1, rng.uniform(0, 1, (STEPS, 1))], axis=1).astype(np.float32)
            front = np.stack([_frame(episode, t, HEIGHT, WIDTH) for t in range(STEPS)])
            wrist = np.stack([_frame(episode, t, 16, 16)[::-1] for t in range(STEPS)])
            for t in range(STEPS):
                frame = {"observation.state": state[t], "action": action[t], "task": TASKS[task]}
                dataset.add_frame({**frame, "observation.images.front": front[t], "observation.images.wrist": wrist[t]})
            dataset.save_episode(parallel_encoding=False)
            for key, value in zip(given, (state, action, front, wrist, task), strict=True):
                given[key].append(value)
        dataset.finalize()
    return SimpleNamespace(root=root, **given)


@pytest.fixture(scope="module")
def imported(source, tmp_path_factory):
    """The dataset imported with 2 episodes of each task held out, cameras at 16 px."""
    out = tmp_path_factory.mktemp("imported") / "robot.zarr"
    main(["lerobot", "import", str(source.root), "--out", str(out), "--image-size", "16", "--holdout-episodes", "2"])
    return EpisodeStore(out), EpisodeStore(out.with_name("robot-heldout.zarr"))


def _resized(frames: np.ndarray, size: int) -> np.ndarray:
    from PIL import Image

    return np.stack([library.fit_image(Image.fromarray(f), size) for f in frames])


def test_an_imported_dataset_has_its_tasks_keys_cameras_and_held_out_episodes(source, imported):
    train, held = imported
    assert train.benchmark == held.benchmark == "lerobot_dataset"
    assert [t["instruction"] for t in train.tasks] == TASKS == [t["instruction"] for t in held.tasks]
    assert train.tasks[0]["id"] == "0000-pick-up-the-red-cube"
    assert sorted(train.keys) == ["action", "camera0", "camera1", "state"]
    assert train.config["fps"] == FPS and train.config["cameras"] == ["camera0", "camera1"]
    assert train.config["features"]["camera1"]["feature"] == "observation.images.wrist"
    # per task, its first two episodes train and its last two are held out
    per_task = {t: [e for e in range(12) if e % 3 == t] for t in range(3)}
    assert sorted(train.column("lerobot_episode")) == sorted(e for eps in per_task.values() for e in eps[:2])
    assert sorted(held.column("lerobot_episode")) == sorted(e for eps in per_task.values() for e in eps[2:])
    for store in (train, held):
        for episode, original in enumerate(store.column("lerobot_episode")):
            steps = store.episode(episode)
            assert store.tasks[int(store.column("task_index")[episode])]["instruction"] == TASKS[source.task[original]]
            np.testing.assert_array_equal(steps["state"], source.state[original])
            np.testing.assert_array_equal(steps["action"], source.action[original])
            np.testing.assert_array_equal(steps["camera1"], _resized(source.wrist[original], 16))  # PNG: exact
            front = _resized(source.front[original], 16).astype(int)
            assert np.abs(steps["camera0"].astype(int) - front).mean() < 6  # a lossy video, decoded
            assert np.abs(steps["camera0"][-1].astype(int) - front[0]).mean() > 10  # ... of the right step
    assert BENCHMARK.frames(train, 1, "camera0", 32, steps=[0, 5]).shape == (2, 32, 32, 3)
    from PIL import Image

    padded = library.fit_image(Image.fromarray(source.front[0][0]), 16, "pad")  # 24x32 -> 12x16, black above and below
    assert padded[:2].max() == padded[-2:].max() == 0 and padded[2:14].min() > 0
    with pytest.raises(ValueError, match="has the cameras camera0, camera1; got 'image'"):
        BENCHMARK.frames(train, 0, "image", 16)


def test_some_episodes_and_features_import_alone(source, tmp_path, capsys):
    out = tmp_path / "part.zarr"
    main(
        [
            "lerobot",
            "import",
            str(source.root),
            "--out",
            str(out),
            "--episodes",
            "7,3",
            "--skip",
            "wrist",
            "--fit",
            "pad",
        ]
    )
    part = EpisodeStore(out)
    assert list(part.column("lerobot_episode")) == [3, 7] and sorted(part.keys) == ["action", "camera0", "state"]
    np.testing.assert_array_equal(part.episode(1)["state"], source.state[7])
    assert part["camera0"].shape[1:] == (96, 96, 3) and part["camera0"][:, :12].max() == 0  # padded above


def _copy(source, tmp_path: Path) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(source.root, copy)
    return copy


def test_datasets_bpp_cannot_read_are_refused_with_what_is_wrong(source, tmp_path, capsys):
    out = str(tmp_path / "s.zarr")
    copy = _copy(source, tmp_path)
    info = json.loads((copy / "meta" / "info.json").read_text())
    (copy / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    with pytest.raises(SystemExit, match="codebase_version v2.1; bpp reads LeRobot v3 datasets"):
        main(["lerobot", "import", str(copy), "--out", out])
    text = {"dtype": "string", "shape": (1,), "names": None}
    (copy / "meta" / "info.json").write_text(json.dumps({**info, "features": {**info["features"], "note": text}}))
    with pytest.raises(SystemExit, match="feature 'note' has dtype 'string'.*--skip note"):
        main(["lerobot", "import", str(copy), "--out", out])
    (copy / "meta" / "info.json").write_text(json.dumps(info))
    for video in (copy / "videos").rglob("*.mp4"):
        video.unlink()
    with pytest.raises(SystemExit, match="missing video file videos/observation.images.front/.*--skip"):
        main(["lerobot", "import", str(copy), "--out", out])
    with pytest.raises(SystemExit, match="--cameras 'side' is not a feature of the dataset"):
        main(["lerobot", "import", str(source.root), "--out", out, "--cameras", "side"])
    with pytest.raises(SystemExit, match="no such folder, and no dataset of that name in LeRobot's cache"):
        main(["lerobot", "import", "nobody/nothing", "--out", out])
    with pytest.raises(SystemExit, match="imported, not generated: bpp lerobot import"):
        main(["lerobot", "generate", "--out", out])
    assert not Path(out).exists()


def _data_file(root: Path) -> Path:
    (path,) = sorted((root / "data").glob("*/*.parquet"))
    return path


def _rewrite_column(root: Path, column: str, change) -> None:
    """Rewrite the dataset's per-frame parquet file with `change` applied to `column`'s (frames, width) values."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = _data_file(root)
    table = pq.read_table(path)
    field = table.schema.field(column)
    values = np.stack(table.column(column).to_pylist()).astype(np.float32)
    changed = pa.array(list(change(values)), type=field.type)
    pq.write_table(table.set_column(table.schema.get_field_index(column), field, changed), path)


@pytest.mark.parametrize(
    "column, value, frame",
    [("action", np.nan, 13), ("observation.state", np.inf, 0), ("observation.state", -np.inf, 57)],
)
def test_non_finite_numbers_are_refused_naming_the_file_column_and_frame(source, tmp_path, column, value, frame):
    copy = _copy(source, tmp_path)

    def poison(values):
        values[frame, 1] = value
        return values

    _rewrite_column(copy, column, poison)
    out = tmp_path / "s.zarr"
    episode, in_episode = divmod(frame, STEPS)
    pattern = (
        rf"{_data_file(copy)} \(episode {episode}\): column '{column}' holds {value} at frame {in_episode} \(value 1\)"
    )
    with pytest.raises(SystemExit, match=pattern):
        main(["lerobot", "import", str(copy), "--out", str(out)])
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["copy"]


def test_damaged_files_and_metadata_are_refused_naming_the_file(source, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = str(tmp_path / "s.zarr")
    copy = _copy(source, tmp_path)
    info_path = copy / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    for fps in (0, -10, "ten", None):
        info_path.write_text(json.dumps({**info, "fps": fps}))
        with pytest.raises(SystemExit, match=f"info.json: fps {fps!r}; a dataset's frame rate is a positive number"):
            main(["lerobot", "import", str(copy), "--out", out])
    info_path.write_text(json.dumps(info))
    data = _data_file(copy)
    whole = data.read_bytes()
    table = pq.read_table(data)
    # a renamed column, a narrower one
    pq.write_table(table.rename_columns(["actions" if n == "action" else n for n in table.column_names]), data)
    with pytest.raises(SystemExit, match=rf"{data}: no column 'action', a feature of meta/info.json"):
        main(["lerobot", "import", str(copy), "--out", out])
    narrow = pa.array([row[:2] for row in table.column("observation.state").to_pylist()], pa.list_(pa.float32(), 2))
    state = table.schema.get_field_index("observation.state")
    pq.write_table(table.set_column(state, pa.field("observation.state", narrow.type), narrow), data)
    with pytest.raises(SystemExit, match=rf"{data}: column 'observation.state' holds 2 values a frame, .* says 3"):
        main(["lerobot", "import", str(copy), "--out", out])
    # an episode the metadata lists whose frames are gone
    pq.write_table(table.filter(pa.compute.not_equal(table.column("episode_index"), 1)), data)
    gone = rf"{data}: episode 1 has 0 frames there, meta/episodes lists {STEPS}; the dataset is damaged"
    with pytest.raises(SystemExit, match=gone):
        main(["lerobot", "import", str(copy), "--out", out])
    # truncated, and garbled in the middle of its pages
    data.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(SystemExit, match=rf"{data}: not a readable parquet file"):
        main(["lerobot", "import", str(copy), "--out", out])
    middle = len(whole) // 3
    data.write_bytes(whole[:middle] + bytes(255 - b for b in whole[middle : middle + 2000]) + whole[middle + 2000 :])
    relative = data.relative_to(copy)
    named = rf"{copy}(: a parquet file under data/ is damaged .*{relative}|/{relative}: .*damaged)"
    with pytest.raises(SystemExit, match=named):
        main(["lerobot", "import", str(copy), "--out", out])
    assert [p.name for p in tmp_path.iterdir()] == ["copy"]


def test_importing_and_exporting_write_nothing_outside_the_output(source, imported, home_cache, tmp_path, capsys):
    out = tmp_path / "in" / "robot.zarr"
    main(["lerobot", "import", str(source.root), "--out", str(out), "--episodes", "0:2", "--image-size", "32"])
    main(["lerobot", "export", str(out), "--out", str(tmp_path / "out" / "robot")])
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == ["robot.zarr"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["robot"]
    assert list(Path(home_cache).iterdir()) == []


def test_export_on_a_full_disk_names_the_dataset_and_leaves_nothing(debug_store, tmp_path, monkeypatch):
    lib = library.dataset_library()

    def save_episode(self, *args, **kwargs):
        (Path(self.root) / "data").mkdir(parents=True, exist_ok=True)
        (Path(self.root) / "data" / "half.parquet").write_bytes(b"PAR1")
        raise OSError(errno.ENOSPC, "No space left on device")  # as pyarrow or FFmpeg's pipe report it

    monkeypatch.setattr(lib.LeRobotDataset, "save_episode", save_episode)
    out = tmp_path / "exports" / "draw"
    with pytest.raises(SystemExit) as stop:
        main(["lerobot", "export", str(debug_store.path), "--out", str(out), "--episodes", "0:1", "--image-size", "32"])
    assert stop.value.code == f"bpp lerobot export: error: {out}: No space left on device"
    assert list((tmp_path / "exports").iterdir()) == []


def test_an_imported_store_exports_under_its_original_feature_names(imported, tmp_path, capsys):
    train, _ = imported
    with pytest.raises(SystemExit, match="--image-size 16: LeRobot's default video encoder .* at least 32 px"):
        main(["lerobot", "export", str(train.path), "--out", str(tmp_path / "again")])  # its frames are 16 px
    main(["lerobot", "export", str(train.path), "--out", str(tmp_path / "again"), "--no-video"])
    info = json.loads((tmp_path / "again" / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS and info["robot_type"] == "arm"
    assert info["features"]["observation.state"]["names"] == ["x", "y", "z"]
    assert info["features"]["observation.images.wrist"]["shape"] == [16, 16, 3]
    main(["lerobot", "import", str(tmp_path / "again"), "--out", str(tmp_path / "back.zarr"), "--image-size", "16"])
    back = EpisodeStore(tmp_path / "back.zarr")
    assert back.keys == train.keys and back.tasks == train.tasks
    for key in back.keys:
        np.testing.assert_array_equal(back.array(key), train.array(key), err_msg=key)


class ReplayingAgent:
    """An agent that outputs, at every step, the recorded action of the episode each rollout replays, plus `offset`."""

    def __init__(self, store: EpisodeStore, replayed: list[int], offset: float = 0.0):
        self.data_spec = DataSpec(lowdim_keys=("state",))
        self.obs_keys = ["state"]
        self.actions = [store.episode(e, ["action"])["action"] for e in replayed]
        self.offset, self.t = offset, 0

    def act_batch(self, obs):
        assert obs["state"].shape == (len(self.actions), 3)
        self.t += 1
        return np.stack([a[min(self.t - 1, len(a) - 1)] + self.offset for a in self.actions])


def test_open_loop_rollouts_score_the_action_error_against_another_episode_of_the_task(imported):
    _, held = imported
    episodes = held.task_episodes()
    rollouts = [
        {"target_episode": int(episodes[0][0]), "prompt_episode": int(episodes[0][0])},  # own prompt
        {"target_episode": int(episodes[1][1]), "prompt_episode": int(episodes[2][0])},  # another task's
    ]
    replayed = [replayed_episode(held, r["target_episode"], r["prompt_episode"]) for r in rollouts]
    assert replayed == [int(episodes[0][1]), int(episodes[1][0])]
    results = run_rollouts(ReplayingAgent(held, replayed), held, rollouts, 100, [True, False], BENCHMARK.frames)
    assert [r.score for r in results] == [0.0, 0.0] and [r.extra["replayed_episode"] for r in results] == replayed
    assert results[0].steps == STEPS and results[0].frames[0].shape == (256, 256, 3) and results[1].frames == []
    stats = held.stats["action"]
    half = (np.asarray(stats["max"]) - np.asarray(stats["min"])) / 2
    results = run_rollouts(ReplayingAgent(held, replayed, 0.1), held, rollouts, 4, [False, False], BENCHMARK.frames)
    np.testing.assert_allclose([r.score for r in results], np.mean(0.1 / half), rtol=1e-5)
    assert results[0].steps == 4 and results[0].extra["action_mae_raw"] == pytest.approx(0.1, rel=1e-5)


def test_a_task_with_one_episode_cannot_be_replayed_without_its_prompt(tmp_path):
    with EpisodeWriter(tmp_path / "one.zarr", benchmark="lerobot_dataset") as writer:
        for task, episodes in enumerate((1, 2)):
            index = writer.add_task(f"task-{task}")
            for _ in range(episodes):
                writer.add_episode({"state": np.zeros((3, 2)), "action": np.zeros((3, 2))}, index)
    store = EpisodeStore(tmp_path / "one.zarr")
    assert replayed_episode(store, 1, 1) == 2
    with pytest.raises(ValueError, match="task 'task-0' has one episode; open-loop evaluation replays"):
        replayed_episode(store, 0, 0)


@pytest.mark.slow
def test_bpp_trains_on_an_imported_dataset_and_is_evaluated_open_loop_with_the_other_task_control(
    imported, tmp_path, capsys
):
    train, held = imported
    run = tmp_path / "run"
    main(
        ["train", "--method", "bpp", "--preset", "debug", "--data", str(train.path), "--out", str(run)]
        + ["--steps", "3", "--batch-size", "4", "--workers", "0", "--model.action-relative-to", "state"]
    )
    config = json.loads((run / "config.json").read_text())["model_config"]
    assert config["obs"]["image_keys"] == ["camera0"] and config["obs"]["proprio_keys"] == ["state"]
    scores = {}
    for prompts in ("own", "other-task"):
        out = tmp_path / prompts
        main(["eval", str(run), "--tasks", str(held.path), "--rollouts", "2", "--workers", "1", "--prompts", prompts]
             + ["--out", str(out)])  # fmt: skip
        results = json.loads((out / "results.json").read_text())
        assert results["metric"]["name"] == "action error" and results["summary"]["tasks"] == 3
        rows = results["rollouts"]
        assert all(r["replayed_episode"] != r["prompt_episode"] for r in rows)
        assert all(r["steps"] == STEPS and np.isfinite(r["score"]) for r in rows)
        scores[prompts] = [r["score"] for r in rows]
        assert (out / "grid.png").is_file()
    assert scores["own"] != scores["other-task"]  # the same replayed episodes, other prompts


def test_a_drawanything_store_exports_to_a_dataset_lerobot_loads_and_imports_back(debug_store, tmp_path, capsys):
    from bpp.benchmarks.draw.benchmark import BENCHMARK as DRAW

    out = tmp_path / "draw"
    main(["lerobot", "export", str(debug_store.path), "--out", str(out), "--image-size", "32", "--episodes", "0:4"])
    lib = library.dataset_library()
    with library.offline_and_quiet(out):
        dataset = lib.LeRobotDataset("bpp/draw", root=out, video_backend="pyav")
    n = int(debug_store.episode_ends[3])
    assert dataset.num_episodes == 4 and dataset.num_frames == n and dataset.fps == 10
    assert list(dataset.meta.tasks.index) == [t["id"] for t in debug_store.tasks[:2]]  # no instructions: the ids
    assert dataset.meta.features["observation.images.image"]["dtype"] == "video"
    # The board-frame actions are actions to LeRobot too: a policy trained on the dataset must not observe them.
    assert dataset.meta.features["action.on_board"]["shape"] == dataset.meta.features["action"]["shape"]
    assert not [name for name in dataset.meta.features if name.startswith("observation.action")]
    table = dataset.hf_dataset.with_format("arrow")[:]
    for key in debug_store.keys:  # every per-step array, as LeRobot reads it
        name = "action" if key == "action" else action_feature(key) if "action" in key else f"observation.{key}"
        values = np.asarray(table.column(name).to_pylist()).reshape(n, -1)
        np.testing.assert_array_equal(values, debug_store.array(key)[:n].reshape(n, -1), err_msg=key)
    main(["lerobot", "import", str(out), "--out", str(tmp_path / "back.zarr"), "--image-size", "32"])
    back = EpisodeStore(tmp_path / "back.zarr")
    assert back.num_episodes == 4 and [t["instruction"] for t in back.tasks] == [t["id"] for t in debug_store.tasks[:2]]
    np.testing.assert_array_equal(back.column("task_index"), debug_store.column("task_index")[:4])
    for key in debug_store.keys:
        np.testing.assert_array_equal(back.array(key), debug_store.array(key)[:n], err_msg=key)
    for episode in range(4):
        drawn = DRAW.frames(debug_store, episode, "image", 32).astype(int)
        assert np.abs(back.episode(episode, ["camera0"])["camera0"] - drawn).mean() < 8  # AV1 video, lossy


def test_lerobots_own_loader_returns_every_exported_array(debug_store, tmp_path, capsys):
    """With images in the parquet files (lossless), LeRobotDataset's items are exactly the store's arrays and
    DrawAnything's frames."""
    from bpp.benchmarks.draw.benchmark import BENCHMARK as DRAW

    out = tmp_path / "draw"
    main(["lerobot", "export", str(debug_store.path), "--out", str(out), "--episodes", "0", "--no-video"])
    with pytest.raises(SystemExit, match="already exists; pass --overwrite"):
        main(["lerobot", "export", str(debug_store.path), "--out", str(out)])
    main(["lerobot", "export", str(debug_store.path), "--out", str(out), "--image-size", "24", "--no-video"]
         + ["--episodes", "5,6", "--overwrite"])  # fmt: skip
    lib = library.dataset_library()
    with library.offline_and_quiet(out):
        dataset = lib.LeRobotDataset("bpp/draw", root=out, video_backend="pyav")
    assert dataset.num_episodes == 2 and dataset.meta.features["observation.images.image"]["dtype"] == "image"
    index = 0
    for episode in (5, 6):
        steps = debug_store.episode(episode)
        frames = DRAW.frames(debug_store, episode, "image", 24)
        task = debug_store.tasks[int(debug_store.column("task_index")[episode])]["id"]
        for t in range(len(frames)):
            item = dataset[index]
            index += 1
            assert item["task"] == task and int(item["frame_index"]) == t
            image = (item["observation.images.image"].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(image, frames[t])
            for key, values in steps.items():
                name = "action" if key == "action" else action_feature(key) if "action" in key else f"observation.{key}"
                got = item[name].numpy().reshape(-1)  # LeRobot's items are float32 tensors, also of float64 columns
                np.testing.assert_array_equal(got, values[t].reshape(-1).astype(got.dtype), err_msg=key)
    assert index == len(dataset)


def test_a_libero_gen_store_with_its_cameras_exports_to_a_dataset_lerobot_loads(tmp_path, capsys):
    """A store of LIBERO-Gen's keys with agent-view frames stored as generation renders them (made here: generating
    one in LIBERO takes minutes); the wrist camera, which it did not store, is left out, so LIBERO itself is not
    needed."""
    rng = np.random.default_rng(0)
    path = tmp_path / "libero.zarr"
    with EpisodeWriter(path, benchmark="libero_gen", stats_keys=("action", "proprio", "object_state")) as writer:
        task = writer.add_task("train-000", {"problem": "(define)"}, instruction="put the bowl on the plate")
        for seed in range(2):
            steps = {
                "action": rng.uniform(-1, 1, (12, 7)).astype(np.float32),
                "action_abs": rng.uniform(-1, 1, (12, 7)).astype(np.float32),
                "executed_action": rng.uniform(-1, 1, (12, 7)).astype(np.float32),
                "proprio": rng.normal(size=(12, 39)).astype(np.float32),
                "object_state": rng.normal(size=(12, 70)).astype(np.float32),
                "sim_state": rng.normal(size=(12, 92)),
                "agentview": rng.integers(0, 255, (12, 32, 32, 3), dtype=np.uint8),
            }
            writer.add_episode(steps, task, seed=seed)
    store = EpisodeStore(path)
    export_store(store, tmp_path / "out", cameras=["agentview"], progress=False)
    lib = library.dataset_library()
    with library.offline_and_quiet(tmp_path / "out"):
        dataset = lib.LeRobotDataset("bpp/libero", root=tmp_path / "out", video_backend="pyav")
    features = dataset.meta.features
    assert dataset.fps == 20 and dataset.num_frames == 24 and dataset.meta.robot_type == "libero_gen"
    assert list(dataset.meta.tasks.index) == ["put the bowl on the plate"]
    assert features["observation.images.agentview"]["shape"] == (32, 32, 3)
    assert features["observation.state"]["shape"] == (39 + 70,)  # the default observation's proprio, object_state
    assert features["observation.sim_state"]["dtype"] == "float64"
    assert "observation.eef" not in features  # derived from the proprioception, not stored
    # Position goals and the executed (noisy) actions are actions, not observations, to LeRobot's policies.
    assert features["action.abs"]["shape"] == features["action.executed_action"]["shape"] == (7,)
    assert not [name for name in features if name.startswith("observation.") and "action" in name]
    table = dataset.hf_dataset.with_format("arrow")[:]
    state = np.asarray(table.column("observation.state").to_pylist(), dtype=np.float32)
    np.testing.assert_array_equal(state, np.concatenate([store.array("proprio"), store.array("object_state")], 1))


def test_action_like_keys_are_named_as_actions_and_names_that_would_clash_are_refused(tmp_path, capsys):
    """Which keys are actions (an observation preset's action key, a name with the word action) and what they are
    called: the store's own action too, when --action exports another key."""
    presets = SimpleNamespace(observations={"canvas": SimpleNamespace(action_key="target_in_canvas")})
    assert [k for k in ("target_in_canvas", "executed_action", "transaction", "tip") if _action_like(presets, k)] == [
        "target_in_canvas",
        "executed_action",
    ]
    assert [action_feature(k) for k in ("action_abs", "target_in_canvas", "action")] == [
        "action.abs",
        "action.target_in_canvas",
        "action.action",
    ]
    rng = np.random.default_rng(0)
    path = tmp_path / "libero.zarr"
    with EpisodeWriter(path, benchmark="libero_gen", stats_keys=("action",)) as writer:
        task = writer.add_task("train-000", {"problem": "(define)"}, instruction="put the bowl on the plate")
        steps = {k: rng.uniform(-1, 1, (6, 7)).astype(np.float32) for k in ("action", "action_abs", "proprio")}
        writer.add_episode(steps, task, seed=0)
    store = EpisodeStore(path)
    export_store(store, tmp_path / "abs", action="action_abs", cameras=[], state=["proprio"], progress=False)
    lib = library.dataset_library()
    with library.offline_and_quiet(tmp_path / "abs"):
        table = lib.LeRobotDataset("bpp/abs", root=tmp_path / "abs").hf_dataset.with_format("arrow")[:]
    for name, key in (("action", "action_abs"), ("action.action", "action"), ("observation.proprio", "proprio")):
        np.testing.assert_array_equal(np.asarray(table.column(name).to_pylist()), store.array(key), err_msg=name)
    path = tmp_path / "clash.zarr"
    with EpisodeWriter(path, benchmark="libero_gen", stats_keys=("action",)) as writer:
        task = writer.add_task("train-000", {"problem": "(define)"}, instruction="put the bowl on the plate")
        writer.add_episode({k: np.zeros((4, 7), np.float32) for k in ("action", "action_abs", "action_action")}, task)
    with pytest.raises(
        UserError, match="keys action and action_action would both be the LeRobot feature 'action.action'"
    ):
        export_store(EpisodeStore(path), tmp_path / "clash", action="action_abs", cameras=[], progress=False)
    assert not (tmp_path / "clash").exists()
