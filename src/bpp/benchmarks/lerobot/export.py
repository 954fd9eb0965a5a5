"""Export any episode store (DrawAnything, LIBERO-Gen, an imported LeRobot dataset) as a LeRobot v3 dataset, written
with LeRobot's own dataset library, so that LeRobot's and openpi's training code read it.

    bpp lerobot export data/libero/train.zarr --out exports/libero-train --cameras agentview eye_in_hand

What becomes what:

* each episode an episode, each task a LeRobot task: its instruction (``--task-text instruction``, the default; a
  task without one gives its id) or its id;
* the action key (the benchmark's default observation's, or ``--action``) becomes ``action``;
* another action-like key (an action key of another of the benchmark's observation presets, or a key with the word
  action in its name, such as LIBERO-Gen's ``action_abs`` and ``executed_action``) becomes ``action.K``, without a
  leading ``action_`` (``action.abs``; the store's own ``action`` when another key is the action: ``action.action``),
  LeRobot's own namespace for action features: LeRobot's policies read ``action`` only, and a future action must not
  reach them as an observation. An import names them by its own rule (``action.abs`` -> ``action_abs``, but
  ``action.executed_action`` -> ``action_executed_action``);
* every other stored per-step key ``K`` becomes ``observation.K`` (float64 stays float64), and ``observation.state``
  is the concatenation of ``--state`` keys (default: the keys the benchmark's default observation preset reads)
  unless the store has a key named ``state``;
* cameras become ``observation.images.<camera>`` videos (``--no-video``: PNG images inside the parquet files,
  lossless; ``--vcodec h264`` for H.264), drawn by the store's benchmark at ``--image-size`` (LIBERO-Gen renders
  cameras it did not store from the stored simulator states);
* a store imported from LeRobot gets its features' original names, dtypes and shapes back.

Per-episode columns (a board angle, a seed) and per-task arrays (a drawing's strokes) have no place in the format and
are left out. The dataset is written into a hidden folder beside ``--out`` and renamed into place when complete.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.lerobot.features import Mapped
from bpp.benchmarks.lerobot.importer import BENCHMARK as IMPORTED
from bpp.benchmarks.lerobot.library import dataset_library, offline_and_quiet
from bpp.core.registry import get_benchmark
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.utils import naming

CONTROL_HZ = {"drawanything": 10, "libero_gen": 20}
"""Control rates of the built-in simulators (DrawAnything's physics.CONTROL_HZ; LIBERO's control_freq), the fps of
their exports; other stores without an ``fps`` in their config default to 10."""
VCODECS = ("libsvtav1", "h264")
"""Video codecs of LeRobot's writer offered here: libsvtav1 (AV1, its default) and h264. (Its third, hevc, crashes
PyAV's FFmpeg on some small frame sizes, 40 and 48 px among them.)"""
MIN_AV1_SIZE = 32
"""SVT-AV1 stops the process (a floating-point exception) on frames under 28 px; smaller exports are refused."""


def _imported(store: EpisodeStore) -> dict[str, Mapped]:
    """A store imported from LeRobot: its keys' original features (none for other stores)."""
    if store.benchmark != IMPORTED:
        return {}
    return {key: Mapped.from_json(spec) for key, spec in store.config.get("features", {}).items()}


def default_cameras(store: EpisodeStore) -> list[str]:
    """The cameras an export draws by default: an imported store's own, else every camera the store's benchmark's
    observation presets name (in their order)."""
    if store.benchmark == IMPORTED:
        return list(store.config.get("cameras", []))
    cameras: list[str] = []
    for preset in get_benchmark(store.benchmark).observations.values():
        cameras += [key for key in preset.image_keys if key not in cameras]
    return cameras


def _default_state(store: EpisodeStore, keys: Sequence[str]) -> list[str]:
    """The keys the benchmark's default observation preset reads, those of them the store has."""
    benchmark = get_benchmark(store.benchmark)
    preset = benchmark.observations[benchmark.default_observation("cpu")]
    return [k for k in (*preset.proprio_keys, *preset.lowdim_keys) if k in keys]


def _task_texts(store: EpisodeStore, task_text: str) -> list[str]:
    texts = [(task["instruction"] or task["id"]) if task_text == "instruction" else task["id"] for task in store.tasks]
    repeated = sorted({t for t in texts if texts.count(t) > 1})
    if repeated:
        raise UserError(
            f"{store.path}: several tasks would share the LeRobot task {repeated[0]!r} (LeRobot keys tasks by their "
            "text); export with --task-text id"
        )
    return texts


def export_store(
    store: EpisodeStore,
    out: Path,
    *,
    cameras: Sequence[str] | None = None,
    image_size: int = 0,
    video: bool = True,
    vcodec: str = "libsvtav1",
    action: str = "",
    state: Sequence[str] | None = None,
    task_text: str = "instruction",
    fps: int = 0,
    episodes: Sequence[int] | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Write `store` (or its `episodes`) as a LeRobot v3 dataset at `out`; see the module docstring. Returns `out`."""
    lib = dataset_library()  # a missing extra is named before anything else
    out = Path(out)
    if out.exists() and not overwrite:
        raise UserError(f"{out} already exists; pass --overwrite to replace it")
    if out.exists() and not (out / "meta" / "info.json").is_file():
        raise UserError(f"{out} exists and is not a LeRobot dataset; only a dataset is ever replaced")
    if vcodec not in VCODECS:
        raise UserError(f"--vcodec must be one of {', '.join(VCODECS)}, got {vcodec!r}")
    benchmark = get_benchmark(store.benchmark)
    origin = _imported(store)
    stored = [k for k in store.keys if k not in store.derived]
    action = action or ("action" if origin else benchmark.observations[benchmark.default_observation("cpu")].action_key)
    if action not in store.keys:
        raise UserError(f"{store.path} has no action key {action!r} (--action); its keys: {', '.join(store.keys)}")
    cameras = list(default_cameras(store) if cameras is None else cameras)
    size = image_size or _stored_size(store, cameras) or 128
    if video and cameras and vcodec == "libsvtav1" and size < MIN_AV1_SIZE:
        raise UserError(
            f"--image-size {size}: LeRobot's default video encoder (SVT-AV1) needs frames of at least {MIN_AV1_SIZE} "
            "px; export with --vcodec h264, --no-video or a larger --image-size"
        )
    episodes = list(range(store.num_episodes)) if episodes is None else [int(e) for e in episodes]
    for e in episodes:
        store.episode_slice(e)  # an error naming the store's episode count if out of range
    for camera in cameras:  # every camera is checked before anything is written
        try:
            benchmark.frames(store, episodes[0], camera, size, last_only=True)
        except ValueError as err:
            raise UserError(f"--cameras {camera!r}: {err}") from None
    numeric = [k for k in stored if k != action and k not in cameras and _is_vector(store, k)]
    features = {_name(origin, action, "action"): _vector_feature(store, action, origin)}
    names = {action: _name(origin, action, "action")}
    for key in numeric:
        names[key] = _name(origin, key, action_feature(key) if _action_like(benchmark, key) else f"observation.{key}")
        features[names[key]] = _vector_feature(store, key, origin)
    clash = next((name for name, n in Counter(names.values()).items() if n > 1), None)
    if clash is not None:
        both = [k for k, name in names.items() if name == clash]
        raise UserError(f"{store.path}: keys {' and '.join(both)} would both be the LeRobot feature {clash!r}")
    concat = []
    if "observation.state" not in features:
        concat = list(_default_state(store, store.keys) if state is None else state)
        for key in concat:
            if key not in store.keys or not _is_vector(store, key):
                raise UserError(f"--state {key!r} is not a numeric per-step key of {store.path}")
        if concat:
            width = sum(int(np.prod(store[k].shape[1:])) for k in concat)
            dtype = np.result_type(*(store[k].dtype for k in concat), np.float32)
            features["observation.state"] = {"dtype": str(dtype), "shape": (width,), "names": None}
    elif state:
        raise UserError(f"{store.path} has a key that becomes observation.state already; --state cannot replace it")
    for camera in cameras:
        names[camera] = _name(origin, camera, f"observation.images.{camera}")
        features[names[camera]] = {
            "dtype": "video" if video else "image",
            "shape": (size, size, 3),
            "names": ["height", "width", "channels"],
        }
    scalars = [name for name, f in features.items() if f["dtype"] not in ("video", "image") and f["shape"] == (1,)]
    texts = _task_texts(store, task_text)
    fps = int(fps or store.config.get("fps") or CONTROL_HZ.get(store.benchmark, 10))
    task_index = store.column("task_index")
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with offline_and_quiet(out):
            dataset = lib.LeRobotDataset.create(
                repo_id=f"bpp/{out.name}",
                fps=fps,
                features=features,
                root=tmp,
                robot_type=store.config.get("robot_type") if origin else store.benchmark,
                use_videos=video,
                video_backend="pyav",
                vcodec=vcodec,
            )
            for episode in tqdm(episodes, desc="export", unit="episode", disable=not progress):
                steps = store.episode(episode, [action, *numeric, *concat])
                for key, values in steps.items():
                    if values.dtype.kind == "f" and not np.isfinite(values).all():
                        raise UserError(f"{store.path}: episode {episode}'s {key!r} holds a NaN or an infinity")
                columns = {names[k]: _feature_values(steps[k], features[names[k]]) for k in [action, *numeric]}
                if concat:
                    joined = np.concatenate([steps[k].reshape(len(steps[k]), -1) for k in concat], axis=1)
                    columns["observation.state"] = joined.astype(features["observation.state"]["dtype"])
                for camera in cameras:
                    columns[names[camera]] = benchmark.frames(store, episode, camera, size)
                text = texts[int(task_index[episode])]
                for t in range(len(steps[action])):
                    dataset.add_frame({**{name: values[t] for name, values in columns.items()}, "task": text})
                # One-feature columns go to the parquet writer as scalars, as LeRobot's own bookkeeping columns do:
                # its encoder turns each (1,) value into a Python float, which numpy >= 2.4 refuses for an array.
                for name in scalars:
                    dataset.episode_buffer[name] = [value[0] for value in dataset.episode_buffer[name]]
                dataset.save_episode(parallel_encoding=False)
            dataset.finalize()
        if out.exists():
            old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(out, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp, out)
    except OSError as err:  # a full disk: LeRobot's writer, pyarrow and FFmpeg name the temporary folder or nothing
        raise naming(err, out) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _action_like(benchmark, key: str) -> bool:
    """Whether a stored key holds actions: an observation preset's action key, or a key with the word action in its
    name (``executed_action``, not ``transaction``)."""
    return "action" in key.split("_") or any(preset.action_key == key for preset in benchmark.observations.values())


def action_feature(key: str) -> str:
    """The LeRobot name of an action-like key that is not the exported action: ``action_abs`` -> ``action.abs``,
    ``target_in_canvas`` -> ``action.target_in_canvas``, ``action`` -> ``action.action``."""
    return "action." + key.removeprefix("action_")


def _stored_size(store: EpisodeStore, cameras: Sequence[str]) -> int:
    """The size of the first camera the store holds frames of (0 if none)."""
    for camera in cameras:
        if camera in store.keys and len(store[camera].shape) == 4:
            return int(store[camera].shape[1])
    return 0


def _is_vector(store: EpisodeStore, key: str) -> bool:
    """A numeric per-step key of at most one feature axis (frames and other arrays are not exported as state)."""
    array = store[key]
    return len(array.shape) <= 2 and np.dtype(array.dtype).kind in "biuf"


def _name(origin: dict[str, Mapped], key: str, default: str) -> str:
    return origin[key].feature if key in origin else default


def _vector_feature(store: EpisodeStore, key: str, origin: dict[str, Mapped]) -> dict:
    """A numeric key's LeRobot feature: an imported key's original one, else its own dtype and width."""
    if key in origin:
        m = origin[key]
        return {"dtype": m.dtype, "shape": tuple(m.shape) or (1,), "names": m.names}
    array = store[key]
    return {"dtype": str(array.dtype), "shape": (int(np.prod(array.shape[1:])),), "names": None}


def _feature_values(values: np.ndarray, feature: dict) -> np.ndarray:
    """(T, ...) stored values -> (T, *feature shape) in the feature's dtype."""
    return np.asarray(values).reshape(len(values), *feature["shape"]).astype(np.dtype(feature["dtype"]))
