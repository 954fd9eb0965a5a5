"""Import a LeRobot v3 dataset on disk into an episode store (and optionally a held-out store beside it).

    bpp lerobot import ~/data/my_robot --out data/lerobot/my_robot.zarr --image-size 96 --holdout-episodes 2

The dataset is read with LeRobot's own dataset library (its metadata, tasks, episodes and per-frame table) from a
local folder, or from a dataset LeRobot or the Hugging Face Hub already cached on this machine; nothing is downloaded.
Each LeRobot task becomes a task (its text the task's instruction, so same-task prompts work), each episode an
episode, and the features map to store keys as :mod:`bpp.benchmarks.lerobot.features` says; camera frames are decoded
and resized to one square size when imported.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.lerobot.features import FeatureMap, Mapped, map_features
from bpp.benchmarks.lerobot.library import (
    FITS,
    READ_MAJOR,
    VideoFile,
    dataset_library,
    decode_png,
    fit_image,
    offline_and_quiet,
)
from bpp.data.arrays import first_non_finite
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError
from bpp.recorded.heldout import heldout_path, split_episodes
from bpp.utils import check_fields, read_json

BENCHMARK = "lerobot_dataset"
"""The benchmark name written into imported stores (the registry's key)."""


@dataclass(frozen=True)
class ImportSettings:
    """What to import and how (the flags of ``bpp lerobot import`` besides the source and the output)."""

    image_size: int = 96
    """Side of the square camera frames stored (px)."""
    fit: Literal["stretch", "pad"] = "stretch"
    """How a camera frame becomes square: stretch (resize to the square) or pad (scale to fit, black borders)."""
    cameras: tuple[str, ...] = ()
    """Cameras to import, in the order they become camera0, camera1, ... (full feature names or their last part;
    default: every camera, in the dataset's order)."""
    skip: tuple[str, ...] = ()
    """Features to leave out (e.g. a depth camera or a text column)."""
    action: str = "action"
    """The feature that holds the actions."""
    episodes: str = ""
    """Episodes to import: "" (all), a range "START:STOP" or a list "0,3,7" of LeRobot episode indices."""
    holdout_episodes: int = 0
    """Per task, its last N episodes go to the held-out store (tasks with N or fewer stay whole in training)."""
    holdout_tasks: int = 0
    """The last N tasks (by LeRobot task index) go whole to the held-out store: tasks the policy never trains on."""

    def __post_init__(self):
        check_fields(
            self,
            ("image_size", 8 <= self.image_size <= 1024, "in [8, 1024] px"),
            ("fit", self.fit in FITS, f"one of {', '.join(FITS)}"),
            ("holdout_episodes", self.holdout_episodes >= 0, ">= 0"),
            ("holdout_tasks", self.holdout_tasks >= 0, ">= 0"),
        )


# ------------------------------------------------------------------------------------------------ where it is
def lerobot_home() -> Path:
    """LeRobot's own dataset cache: ``$HF_LEROBOT_HOME``, else ``$HF_HOME/lerobot``."""
    if os.environ.get("HF_LEROBOT_HOME"):
        return Path(os.environ["HF_LEROBOT_HOME"]).expanduser()
    # the Hugging Face Hub's client: the lerobot extra
    from huggingface_hub.constants import HF_HOME

    return Path(HF_HOME) / "lerobot"


def _hub_snapshot(repo_id: str) -> Path | None:
    """The dataset `repo_id` in the Hugging Face Hub's cache: the snapshot ``refs/main`` names, else the newest."""
    # the Hugging Face Hub's client: the lerobot extra
    from huggingface_hub.constants import HF_HUB_CACHE

    folder = Path(HF_HUB_CACHE) / ("datasets--" + repo_id.replace("/", "--"))
    ref = folder / "refs" / "main"
    if ref.is_file() and (folder / "snapshots" / ref.read_text().strip()).is_dir():
        return folder / "snapshots" / ref.read_text().strip()
    snapshots = sorted((folder / "snapshots").glob("*"), key=lambda p: p.stat().st_mtime) if folder.is_dir() else []
    return snapshots[-1] if snapshots else None


def locate(source: str | Path) -> Path:
    """The dataset's root folder: `source` itself if it is a folder, else the repo id `source` in LeRobot's cache or
    the Hugging Face Hub's cache. Nothing is downloaded."""
    path = Path(source).expanduser()
    if path.is_dir():
        return path
    name = str(source)
    if re.fullmatch(r"[\w.-]+/[\w.-]+", name):
        for candidate in (lerobot_home() / name, _hub_snapshot(name)):
            if candidate is not None and candidate.is_dir():
                return candidate
    raise UserError(
        f"{source}: no such folder, and no dataset of that name in LeRobot's cache ({lerobot_home()}) or the Hugging "
        "Face Hub's; nothing is downloaded: fetch it first (e.g. hf download --repo-type dataset REPO_ID --local-dir "
        "DIR) and import the folder"
    )


def read_info(root: Path) -> dict:
    """The dataset's ``meta/info.json``, checked to be a LeRobot v3 dataset whose metadata is all there."""
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise UserError(f"{root}: not a LeRobot dataset (no meta/info.json)")
    info = read_json(info_path, "LeRobot dataset info")
    version = str(info.get("codebase_version", "")) if isinstance(info, dict) else ""
    major = re.match(r"v?([0-9]+)\.", version)
    if not major or int(major.group(1)) != READ_MAJOR:
        raise UserError(
            f"{info_path}: codebase_version {version or 'missing'}; bpp reads LeRobot v{READ_MAJOR} datasets "
            "(v3.0). Convert an older one with LeRobot's converter first (lerobot.datasets.v30."
            "convert_dataset_v21_to_v30)"
        )
    for field in ("fps", "features", "data_path"):
        if field not in info:
            raise UserError(f"{info_path}: no {field!r} entry; the dataset's metadata is damaged")
    for needed in ("meta/tasks.parquet", "meta/episodes"):
        if not (root / needed).exists():
            raise UserError(f"{root}: missing {needed}; the dataset is incomplete")
    fps = info["fps"]
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not math.isfinite(fps) or fps <= 0:
        raise UserError(f"{info_path}: fps {fps!r}; a dataset's frame rate is a positive number")
    return info


def check_data_file(path: Path, fmap: FeatureMap, features: dict) -> np.ndarray:
    """Refuse a per-frame parquet file that cannot be read, or lacks a column bpp imports, or holds it narrower or
    wider than ``meta/info.json`` says, naming the file and the column (LeRobot's library would fail later, in the
    `datasets` package, with a traceback that names neither). Returns its count of frames per episode index."""
    # pyarrow: the lerobot extra
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except (pa.ArrowException, OSError) as err:
        raise UserError(f"{path}: not a readable parquet file ({err}); the dataset is damaged") from None
    for item in (*fmap.lowdim, fmap.action):
        if item.feature not in schema.names:
            raise UserError(f"{path}: no column {item.feature!r}, a feature of meta/info.json; the file is damaged")
        kind = schema.field(item.feature).type
        width = kind.list_size if pa.types.is_fixed_size_list(kind) else None
        expected = int(np.prod(features[item.feature].get("shape") or (1,)))
        if width is not None and width != expected:
            raise UserError(
                f"{path}: column {item.feature!r} holds {width} values a frame, meta/info.json says {expected}"
            )
    try:
        episodes = pq.read_table(path, columns=["episode_index"]).column("episode_index").to_numpy()
    except (pa.ArrowException, OSError, KeyError) as err:
        cause = " ".join(str(err).split())
        raise UserError(f"{path}: cannot read its episode_index column ({cause}); the file is damaged") from None
    if len(episodes) and not (np.isfinite(episodes).all() and episodes.min() >= 0):
        raise UserError(f"{path}: episode_index holds {episodes.min()}; episode indices are 0 or more")
    return np.bincount(episodes.astype(np.int64)) if len(episodes) else np.zeros(0, np.int64)


def _check_finite_frames(values: np.ndarray, where: str, feature: str) -> None:
    """Refuse NaN and infinities where they enter, naming the file, the column and the frame (the store refuses
    them too, but knows neither)."""
    found = first_non_finite(values)
    if found is None:
        return
    frame, item = found
    raise UserError(
        f"{where}: column {feature!r} holds {values[frame, item]} at frame {frame} (value {item}); bpp imports finite "
        "numbers only: repair or drop the episode (--episodes)"
    )


def parse_episodes(text: str, total: int) -> list[int]:
    """``""`` (all), ``"START:STOP"`` or ``"0,3,7"`` -> sorted LeRobot episode indices, each checked."""
    text = text.strip()
    if not text:
        return list(range(total))
    try:
        if ":" in text:
            start, stop = (int(part) if part.strip() else None for part in text.split(":", 1))
            chosen = list(range(total))[slice(start, stop)]
        else:
            chosen = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        raise UserError(f"--episodes {text!r}: expected START:STOP or a comma-separated list of indices") from None
    outside = [e for e in chosen if not 0 <= e < total]
    if outside or not chosen:
        raise UserError(f"--episodes {text!r}: the dataset has episodes 0 to {total - 1}, selected {outside or 'none'}")
    return chosen


# ------------------------------------------------------------------------------------------------ reading
def _as_numpy(column, rows: int, item: Mapped, where: str) -> np.ndarray:
    """An Arrow column of a numeric feature -> (rows, width) in the store's dtype; `where` names the episode's file
    in errors."""
    # pyarrow: the lerobot extra
    import pyarrow as pa

    array = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if isinstance(array.type, pa.ExtensionType):
        array = array.storage
    nested = (pa.types.is_list, pa.types.is_fixed_size_list, pa.types.is_large_list)
    while any(is_nested(array.type) for is_nested in nested):
        array = array.flatten()
    values = array.to_numpy(zero_copy_only=False)
    if values.size != rows * item.width:
        raise UserError(f"{where}: column {item.feature!r}: {values.size} values for {rows} frames of {item.shape}")
    values = values.reshape(rows, item.width)
    _check_finite_frames(values, where, item.feature)
    return values.astype(item.store_dtype)


def _arrow_cause(err: BaseException, root: Path) -> str | None:
    """The Arrow error, or the I/O error on a file of the dataset at `root`, at the bottom of `err`'s chain, as
    "Type: message"; None if there is none (an I/O error elsewhere, e.g. a full disk under the cache, is not the
    dataset's)."""
    # pyarrow: the lerobot extra
    import pyarrow as pa

    found, seen = None, set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        ours = isinstance(err, OSError) and str(root) in f"{err.filename or ''} {err}"
        if isinstance(err, pa.ArrowException) or ours:
            found = f"{type(err).__name__}: {' '.join(str(err).split())}"
        err = err.__cause__ or err.__context__
    return found


class _Reader:
    """Reads episodes of one dataset through LeRobot's library: per-frame arrays, frames and tasks."""

    def __init__(self, root: Path, fmap: FeatureMap, settings: ImportSettings):
        self.root, self.fmap, self.settings = root, fmap, settings
        lib = dataset_library()
        repo_id = f"local/{root.name}"
        self.meta = lib.LeRobotDatasetMetadata(repo_id, root=root)
        self.fps = float(self.meta.fps)
        self.tasks = {int(row["task_index"]): str(text) for text, row in self.meta.tasks.iterrows()}
        self.lib, self.repo_id = lib, repo_id
        self._videos: dict[str, VideoFile] = {}

    @property
    def total_episodes(self) -> int:
        return int(self.meta.total_episodes)

    def open(self, episodes: Sequence[int]) -> None:
        """Load the episodes' per-frame table, once every file the library reads for them is known to be on disk
        (it would try to download a missing one: a file of a dataset it takes to be incomplete)."""
        # the Hugging Face Hub's client: the lerobot extra
        from huggingface_hub.errors import OfflineModeIsEnabled

        frames: dict[Path, np.ndarray] = {}  # each data file's frames per episode index
        for episode in episodes:
            data = self.root / self.meta.get_data_file_path(episode)
            if not data.is_file():
                raise UserError(f"{self.root}: missing data file {data.relative_to(self.root)} (episode {episode})")
            if data not in frames:
                frames[data] = check_data_file(data, self.fmap, self.meta.features)
            listed = int(self.meta.episodes[episode]["length"])
            held = int(frames[data][episode]) if episode < len(frames[data]) else 0
            if listed <= 0:
                raise UserError(
                    f"{self.root}: meta/episodes lists episode {episode} with {listed} frames; an empty episode "
                    "cannot be imported: leave it out with --episodes"
                )
            if held != listed:
                raise UserError(
                    f"{data}: episode {episode} has {held} frames there, meta/episodes lists {listed}; the dataset is "
                    "damaged (leave the episode out with --episodes)"
                )
            for key in self.meta.video_keys:
                video = self.root / self.meta.get_video_file_path(episode, key)
                if not video.is_file():
                    raise UserError(
                        f"{self.root}: missing video file {video.relative_to(self.root)} ({key}, episode {episode}); "
                        "the dataset is incomplete: fetch its videos too (LeRobot's library opens every camera's "
                        "videos of the episodes imported, including cameras left out with --skip)"
                    )
        # All episodes: the library's default, its per-frame table memory-mapped through the `datasets` cache; some:
        # only theirs, read into memory.
        chosen = None if len(episodes) == self.total_episodes else list(episodes)
        try:
            self.dataset = self.lib.LeRobotDataset(
                self.repo_id, root=self.root, episodes=chosen, download_videos=False, video_backend="pyav"
            )
        except OfflineModeIsEnabled:
            raise UserError(
                f"{self.root}: LeRobot's library finds the dataset incomplete; nothing is downloaded"
            ) from None
        except Exception as err:  # noqa: BLE001 - the `datasets` package wraps a damaged file's Arrow error its own way
            cause = _arrow_cause(err, self.root)
            if cause is None:
                raise
            files = sorted({str(self.meta.get_data_file_path(e)) for e in episodes})
            raise UserError(
                f"{self.root}: a parquet file under data/ is damaged ({cause}); the episodes imported read "
                f"{', '.join(files)}"
            ) from None
        self.table = self.dataset.hf_dataset.with_format("arrow")
        columns = self.table[:].select(["episode_index", "frame_index", "task_index"])
        self.frame_episodes, self.frame_numbers, self.frame_tasks = (
            columns.column(name).to_numpy() for name in ("episode_index", "frame_index", "task_index")
        )

    def _positions(self, episode: int) -> np.ndarray:
        """Row numbers of the episode's frames in the per-frame table, in frame order."""
        positions = np.flatnonzero(self.frame_episodes == episode)
        if len(positions) == 0:
            raise UserError(f"{self.root}: episode {episode} has no frames in the dataset's data files")
        return positions[np.argsort(self.frame_numbers[positions], kind="stable")]

    def task(self, episode: int) -> int:
        """The LeRobot task index of an episode: that of its first frame."""
        return int(self.frame_tasks[self._positions(episode)[0]])

    def rows(self, episode: int):
        """The episode's frames as an Arrow table, in frame order."""
        positions = self._positions(episode)
        if np.array_equal(positions, np.arange(positions[0], positions[0] + len(positions))):
            return self.table[int(positions[0]) : int(positions[-1]) + 1]
        return self.dataset.hf_dataset.select(positions).with_format("arrow")[:]

    def read(self, episode: int, table) -> dict[str, np.ndarray]:
        """The store's per-step arrays of one episode."""
        n = table.num_rows
        where = f"{self.root / self.meta.get_data_file_path(episode)} (episode {episode})"
        steps = {m.key: _as_numpy(table.column(m.feature), n, m, where) for m in (*self.fmap.lowdim, self.fmap.action)}
        for camera in self.fmap.cameras:
            steps[camera.key] = self._camera(episode, camera, table)
        return steps

    def _camera(self, episode: int, camera: Mapped, table) -> np.ndarray:
        size, fit = self.settings.image_size, self.settings.fit
        if camera.dtype == "image":
            column = table.column(camera.feature).combine_chunks()
            pairs = zip(column.field("bytes").to_pylist(), column.field("path").to_pylist(), strict=True)
            images = [decode_png(data, path, self.root) for data, path in pairs]
        else:
            path = self.root / self.meta.get_video_file_path(episode, camera.feature)
            if camera.feature not in self._videos or self._videos[camera.feature].path != path:
                if camera.feature in self._videos:
                    self._videos.pop(camera.feature).close()
                self._videos[camera.feature] = VideoFile(path)
            start = float(self.meta.episodes[episode][f"videos/{camera.feature}/from_timestamp"])
            times = start + table.column("timestamp").to_numpy().astype(np.float64)
            images = self._videos[camera.feature].frames_at(times, tolerance=0.5 / self.fps)
        return np.stack([fit_image(image, size, fit) for image in images])

    def close(self) -> None:
        for video in self._videos.values():
            video.close()
        self._videos.clear()


# ------------------------------------------------------------------------------------------------ writing
def import_dataset(
    source: str | Path,
    out: Path,
    settings: ImportSettings = ImportSettings(),
    heldout_out: Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> tuple[EpisodeStore, EpisodeStore | None]:
    """Import the LeRobot dataset at `source` (a folder or a cached repo id) into the store `out`, and its held-out
    episodes (if the settings hold any out) into `heldout_out` (default: ``<out>-heldout.zarr``). Both are written
    atomically. Returns (the training store, the held-out store or None)."""
    dataset_library()  # a missing extra is named before anything else
    out = Path(out)
    root = locate(source)
    info = read_info(root)
    fmap = map_features(info["features"], settings.cameras, settings.skip, settings.action)
    holding_out = bool(settings.holdout_episodes or settings.holdout_tasks)
    held_path = Path(heldout_out) if heldout_out is not None else heldout_path(out)
    with offline_and_quiet(out):
        reader = _Reader(root, fmap, settings)
        try:
            chosen = parse_episodes(settings.episodes, reader.total_episodes)
            reader.open(chosen)
            by_task: dict[int, list[int]] = {}
            for episode in chosen:
                by_task.setdefault(reader.task(episode), []).append(episode)
            train, held, whole = split_episodes(by_task, settings.holdout_episodes, settings.holdout_tasks)
            if whole:
                count = settings.holdout_episodes
                print(f"[import] {len(whole)} task(s) have {count} episodes or fewer and stay whole in training")
            if holding_out and not held:
                raise UserError("nothing is held out: no task has more episodes than --holdout-episodes")
            config = {
                "source": str(root),
                "codebase_version": info.get("codebase_version"),
                "robot_type": info.get("robot_type"),
                "fps": info["fps"],
                "settings": asdict(settings),
                "features": {m.key: m.to_json() for m in fmap.all},
                "cameras": [m.key for m in fmap.cameras],
            }
            task_of = {e: t for t, episodes in by_task.items() for e in episodes}
            stats_keys = [m.key for m in (*fmap.lowdim, fmap.action)]
            writers = [(out, train, "train")] + ([(held_path, held, "held-out")] if holding_out else [])
            with contextlib.ExitStack() as stack:
                opened = []
                for path, episodes, split in writers:
                    writer = EpisodeWriter(
                        path,
                        benchmark=BENCHMARK,
                        config={**config, "split": split},
                        overwrite=overwrite,
                        stats_keys=stats_keys,
                    )
                    opened.append((stack.enter_context(writer), episodes))
                bar = tqdm(total=len(chosen), desc="import", unit="episode", disable=not progress)
                for writer, episodes in opened:
                    task_index: dict[int, int] = {}
                    for episode in episodes:
                        task = task_of[episode]
                        if task not in task_index:
                            text = reader.tasks.get(task, "")
                            task_index[task] = writer.add_task(
                                _task_id(task, text), {"lerobot_task_index": task}, instruction=text
                            )
                        steps = reader.read(episode, reader.rows(episode))
                        writer.add_episode(steps, task_index[task], lerobot_episode=episode)
                        bar.update()
                bar.close()
        finally:
            reader.close()
    return EpisodeStore(out), (EpisodeStore(held_path) if holding_out else None)


def _task_id(index: int, text: str) -> str:
    """A task's id: its LeRobot index and the start of its text, e.g. ``0003-pick-up-the-cube``."""
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40].rstrip("-")
    return f"{index:04d}-{slug}" if slug else f"{index:04d}"
