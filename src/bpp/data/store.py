"""The episode store: one on-disk format for every benchmark.

Layout (a zarr v3 directory)::

    <name>.zarr/
      zarr.json          attributes: format, version, complete, benchmark, config, tasks, stats, created;
                         tasks is the task table: one {"id", "instruction", "info"} per task
      data/<key>         (N, ...) per-step arrays, episodes concatenated in time, chunked and zstd-compressed
      meta/episode_ends  (E,) int64, exclusive end step of each episode
      meta/<column>      (E,) the episode table: task_index and any per-episode parameters
      tasks/<key>        ragged per-task arrays (e.g. a task's waypoints), with tasks/<key>__ends (K,)

A benchmark may also declare *derived* per-step keys (:attr:`bpp.benchmarks.contract.Benchmark.derived_keys`):
chosen features of a stored key, read and normalised like a stored key but never written. A store finds them through
the registry from its own benchmark name, so every process that opens it sees the same keys.

Writing is atomic: everything goes into a hidden ``.<name>.partial-<id>`` sibling, ``complete`` is set last,
and only then is the folder renamed into place — an interrupted generation never leaves a store that loads
as complete. Reading is safe from many data-loader processes: the store is read-only once written, and each
process opens its own handles lazily (a pickled store carries only its path).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from bpp.benchmarks.registry import derived_keys
from bpp.errors import UserError
from bpp.utils import read_json, to_dict

FORMAT = "bpp-episodes"
VERSION = 1


class StoreError(UserError):
    """A store is missing, incomplete, of another format/version, or used wrongly."""


class StoreKeyError(StoreError, KeyError):
    """A per-step key or episode column the store does not have (a KeyError too, for callers that look one up)."""

    __str__ = Exception.__str__  # the message as written, not KeyError's quoted form


class EpisodeIndexError(StoreError, IndexError):
    """An episode index outside the store."""


def with_derived(benchmark: str, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`obs` (per-step arrays, features last) plus every derived key of the benchmark named `benchmark` whose source
    it has (the same features a store of that benchmark presents)."""
    derived = {
        key: np.asarray(obs[source])[..., list(features)]
        for key, (source, features) in derived_keys(benchmark).items()
        if source in obs and key not in obs
    }
    return {**obs, **derived}


class _DerivedArray:
    """A derived key's lazy per-step array: indexing reads its source's rows, then selects the features."""

    def __init__(self, source, features: tuple[int, ...]):
        self.source, self.features = source, list(features)
        self.shape = (*source.shape[:-1], len(features))
        self.dtype = source.dtype

    def __getitem__(self, selection) -> np.ndarray:
        return np.asarray(self.source[selection])[..., self.features]

    @property
    def oindex(self):
        return _DerivedOIndex(self)


class _DerivedOIndex:
    def __init__(self, array: _DerivedArray):
        self.array = array

    def __getitem__(self, selection) -> np.ndarray:
        return np.asarray(self.array.source.oindex[selection])[..., self.array.features]


def _json_safe(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def remove_stale_partials(path: Path) -> list[Path]:
    """Delete the hidden ``.<name>.partial-<pid>-<id>`` folders that interrupted writers of `path` left behind: those
    whose process no longer runs. A writer still running keeps its folder. Returns what was deleted."""
    removed = []
    for partial in path.parent.glob(f".{path.name}.partial-*"):
        tag = partial.name.rsplit(".partial-", 1)[1].split("-")
        stale = len(tag) == 2 and tag[0].isdigit() and not _process_alive(int(tag[0]))
        if stale and partial.is_dir():
            shutil.rmtree(partial, ignore_errors=True)
            removed.append(partial)
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _is_store(path: Path) -> bool:
    """Whether `path` is a folder holding an episode store (complete or not), judged by its zarr.json alone."""
    try:
        attrs = read_json(path / "zarr.json", "store header").get("attributes", {})
    except (ValueError, AttributeError):
        return False
    return isinstance(attrs, dict) and attrs.get("format") == FORMAT


class _RunningStats:
    """Per-feature min/max/mean/std over all steps, accumulated in float64."""

    def __init__(self):
        self.n = 0
        self.sum = self.sumsq = self.min = self.max = None

    def update(self, x: np.ndarray) -> None:
        x = x.reshape(len(x), -1).astype(np.float64)
        if self.sum is None:
            self.sum = np.zeros(x.shape[1])
            self.sumsq = np.zeros(x.shape[1])
            self.min = np.full(x.shape[1], np.inf)
            self.max = np.full(x.shape[1], -np.inf)
        self.n += len(x)
        self.sum += x.sum(axis=0)
        self.sumsq += (x * x).sum(axis=0)
        self.min = np.minimum(self.min, x.min(axis=0))
        self.max = np.maximum(self.max, x.max(axis=0))

    def result(self) -> dict[str, list[float]]:
        mean = self.sum / self.n
        std = np.sqrt(np.maximum(self.sumsq / self.n - mean * mean, 0.0))
        return {"min": self.min.tolist(), "max": self.max.tolist(), "mean": mean.tolist(), "std": std.tolist()}


class EpisodeWriter:
    """Builds a store episode by episode; use as a context manager (or call :meth:`close`).

    Args:
        path: the final store path (conventionally ``*.zarr``).
        benchmark: name of the benchmark that produced the data (its registry name).
        config: the generator's resolved configuration, saved for provenance.
        overwrite: replace an existing store (atomically) instead of refusing.
        chunk_steps: time-chunk length of per-step arrays.
        stats_keys: per-step keys to compute normalisation statistics for (default: all numeric keys).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        benchmark: str,
        config: dict | None = None,
        overwrite: bool = False,
        chunk_steps: int = 16384,
        stats_keys: Iterable[str] | None = None,
    ):
        import zarr

        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise StoreError(f"{self.path} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
        if self.path.exists() and not _is_store(self.path):
            raise StoreError(
                f"{self.path} exists and is not an episode store; only a store is ever replaced (delete it yourself "
                "if you mean to)"
            )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_partials(self.path)
        self.tmp = self.path.parent / f".{self.path.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.root = zarr.open_group(str(self.tmp), mode="w")
        self.root.attrs.update(
            {
                "format": FORMAT,
                "version": VERSION,
                "complete": False,
                "benchmark": benchmark,
                "config": _json_safe(config or {}),
            }
        )
        self.overwrite = overwrite
        self.chunk_steps = chunk_steps
        self.stats_keys = None if stats_keys is None else set(stats_keys)
        self._buffer: dict[str, list[np.ndarray]] = {}
        self._buffered = 0
        self._step_spec: dict[str, tuple[tuple[int, ...], np.dtype]] | None = None
        self._stats: dict[str, _RunningStats] = {}
        self._ends: list[int] = []
        self._columns: dict[str, list] = {}
        self._tasks: list[dict] = []
        self._task_ragged: dict[str, list[np.ndarray]] = {}
        self._closed = False

    # ------------------------------------------------------------------ tasks
    def add_task(self, task_id: str, info: dict | None = None, *, instruction: str = "", **ragged: np.ndarray) -> int:
        """Register a task; returns its index. `ragged` arrays (one (n_i, ...) array per key) are stored per task.

        `instruction` is the task in words, for language-conditioned policies ("" if the benchmark has none).
        """
        if self._tasks and set(ragged) != set(self._task_ragged):
            raise StoreError(f"task {task_id!r} has ragged keys {sorted(ragged)}, others {sorted(self._task_ragged)}")
        if any(t["id"] == task_id for t in self._tasks):
            raise StoreError(f"duplicate task id {task_id!r}")
        for key, value in ragged.items():
            self._task_ragged.setdefault(key, []).append(np.asarray(value))
        self._tasks.append({"id": task_id, "instruction": str(instruction), "info": _json_safe(info or {})})
        return len(self._tasks) - 1

    # --------------------------------------------------------------- episodes
    def add_episode(self, steps: dict[str, np.ndarray], task_index: int, **columns: Any) -> None:
        """Append one episode: `steps` maps each per-step key to a (T, ...) array (same T and keys every time)."""
        lengths = {k: len(v) for k, v in steps.items()}
        if len(set(lengths.values())) != 1 or 0 in lengths.values():
            raise StoreError(f"episode arrays must share one non-zero length, got {lengths}")
        if not 0 <= task_index < len(self._tasks):
            raise StoreError(f"task_index {task_index} out of range (have {len(self._tasks)} tasks)")
        spec = {k: (np.asarray(v).shape[1:], np.asarray(v).dtype) for k, v in steps.items()}
        if self._step_spec is None:
            self._step_spec = spec
        elif spec != self._step_spec:
            raise StoreError(f"episode keys/shapes/dtypes {spec} differ from the first episode's {self._step_spec}")
        if self._columns and set(columns) | {"task_index"} != set(self._columns):
            raise StoreError(f"episode columns {sorted(columns)} differ from earlier {sorted(self._columns)}")
        n = next(iter(lengths.values()))
        for key, value in steps.items():
            value = np.asarray(value)
            self._buffer.setdefault(key, []).append(value)
            if np.issubdtype(value.dtype, np.number) and (self.stats_keys is None or key in self.stats_keys):
                self._stats.setdefault(key, _RunningStats()).update(value)
        self._ends.append((self._ends[-1] if self._ends else 0) + n)
        for key, value in {"task_index": task_index, **columns}.items():
            self._columns.setdefault(key, []).append(value)
        self._buffered += n
        if self._buffered >= self.chunk_steps:
            self._flush()

    def _flush(self) -> None:
        if not self._buffered:
            return
        for key, parts in self._buffer.items():
            data = np.concatenate(parts)
            name = f"data/{key}"
            if name not in self.root:
                self._create(name, data, self.chunk_steps)
            self.root[name].append(data)
        self._buffer = {}
        self._buffered = 0

    def _create(self, name: str, example: np.ndarray, chunk_len: int):
        from zarr.codecs import ZstdCodec

        item_bytes = max(int(np.prod(example.shape[1:])) * example.dtype.itemsize, 1)
        rows = int(max(1, min(chunk_len, (8 << 20) // item_bytes)))  # chunks of at most ~8 MB
        return self.root.create_array(
            name,
            shape=(0, *example.shape[1:]),
            chunks=(rows, *example.shape[1:]),
            dtype=example.dtype,
            compressors=ZstdCodec(level=5),
        )

    # --------------------------------------------------------------- finishing
    def close(self) -> EpisodeStore:
        """Write tables and statistics, mark complete, and move the store into place."""
        if self._closed:
            raise StoreError("writer already closed")
        if not self._ends:
            raise StoreError(f"{self.path}: no episodes were added; refusing to write an empty store")
        self._flush()
        self.root.create_array("meta/episode_ends", data=np.asarray(self._ends, dtype=np.int64))
        for key, values in self._columns.items():
            self.root.create_array(f"meta/{key}", data=np.asarray(values))
        for key, parts in self._task_ragged.items():
            self.root.create_array(f"tasks/{key}", data=np.concatenate(parts))
            self.root.create_array(f"tasks/{key}__ends", data=np.cumsum([len(p) for p in parts]).astype(np.int64))
        self.root.attrs.update(
            {
                "tasks": self._tasks,
                "stats": {k: s.result() for k, s in self._stats.items()},
                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "complete": True,
            }
        )
        old = None
        if self.path.exists():
            old = self.path.parent / f".{self.path.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(self.path, old)
        os.replace(self.tmp, self.path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        self._closed = True
        return EpisodeStore(self.path)

    def abort(self) -> None:
        """Discard everything written so far."""
        self._closed = True
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._closed:
            self.close()


class EpisodeStore:
    """Read access to a complete store. Cheap to construct and to pickle; arrays are read lazily.

    ``store["action"]`` is the lazy zarr array of a per-step key; :meth:`array` loads (and caches) it in memory.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.exists():
            raise StoreError(f"{self.path}: no such store")
        if not (self.path / "zarr.json").is_file():
            raise StoreError(f"{self.path}: not an episode store (no zarr.json)")
        try:
            attrs = dict(self._root().attrs)
        except Exception as err:  # noqa: BLE001 - zarr raises JSON, KeyError and its own errors for a bad header
            raise StoreError(
                f"{self.path}: damaged store header ({type(err).__name__}: {err}); generate it again"
            ) from None
        if attrs.get("format") != FORMAT:
            raise StoreError(f"{self.path}: format {attrs.get('format')!r}, expected {FORMAT!r}")
        if attrs.get("version") != VERSION:
            raise StoreError(f"{self.path}: store version {attrs.get('version')}, this bpp reads version {VERSION}")
        if not attrs.get("complete"):
            raise StoreError(f"{self.path}: incomplete store (its generation was interrupted); generate it again")
        self.attrs = attrs
        try:
            self.benchmark: str = attrs["benchmark"]
            self.config: dict = attrs.get("config", {})
            self.tasks: list[dict] = attrs["tasks"]
            self._stored_stats: dict[str, dict[str, list[float]]] = attrs["stats"]
        except KeyError as err:
            raise StoreError(f"{self.path}: damaged store header (no {err} entry); generate it again") from None
        self._cache: dict[str, np.ndarray] = {}
        self._derived: dict[str, tuple[str, tuple[int, ...]]] | None = None
        try:
            self.episode_ends = self._read("meta/episode_ends")
        except KeyError:
            raise StoreError(f"{self.path}: damaged store (no meta/episode_ends); generate it again") from None
        self.episode_starts = np.concatenate([[0], self.episode_ends[:-1]])
        try:
            self._stored_keys: list[str] = sorted(self._root()["data"].array_keys())
        except Exception as err:  # noqa: BLE001
            raise StoreError(
                f"{self.path}: damaged store, cannot list its data ({type(err).__name__}: {err})"
            ) from None
        if len(self.episode_ends) == 0 or np.any(np.diff(self.episode_ends) <= 0) or self.episode_ends[0] <= 0:
            raise StoreError(f"{self.path}: damaged store (meta/episode_ends is not increasing); generate it again")

    def _read(self, name: str, selection: slice = slice(None)) -> np.ndarray:
        """Array `name` of the store (or a slice of its first axis), with a StoreError naming the store and the
        array if a chunk is missing or corrupt (zarr and the zstd codec raise their own errors)."""
        try:
            return np.asarray(self._root()[name][selection])
        except KeyError:
            raise
        except Exception as err:  # noqa: BLE001
            raise StoreError(
                f"{self.path}: damaged store, cannot read {name} ({type(err).__name__}: {err}); generate it again"
            ) from None

    def _root(self):
        # One handle per process: handles are not shared across fork/spawn (see __getstate__).
        handle = getattr(self, "_handle", None)
        if handle is None or handle[0] != os.getpid():
            import zarr

            handle = (os.getpid(), zarr.open_group(str(self.path), mode="r"))
            self._handle = handle
        return handle[1]

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_handle", None)
        state["_cache"] = {}
        state["_derived"] = None  # each process looks them up itself, as when it opens the store
        return state

    # ---------------------------------------------------------------- queries
    @property
    def derived(self) -> dict[str, tuple[str, tuple[int, ...]]]:
        """This store's derived keys: key -> (stored source key, feature indices), its benchmark's
        (:attr:`bpp.benchmarks.contract.Benchmark.derived_keys`) whose source it stores. Looked up on first use, in
        the process that uses the store."""
        if self._derived is None:
            self._derived = {
                key: (source, tuple(features))
                for key, (source, features) in derived_keys(self.benchmark).items()
                if source in self._stored_keys and key not in self._stored_keys
            }
        return self._derived

    @property
    def keys(self) -> list[str]:
        """Per-step keys: stored and derived."""
        return sorted([*self._stored_keys, *self.derived])

    @property
    def stats(self) -> dict[str, dict[str, list[float]]]:
        """Per-feature normalisation statistics of each numeric per-step key, derived keys included."""
        stats = dict(self._stored_stats)
        for key, (source, features) in self.derived.items():
            if source in stats:
                stats[key] = {name: [values[i] for i in features] for name, values in stats[source].items()}
        return stats

    @property
    def num_episodes(self) -> int:
        return len(self.episode_ends)

    @property
    def num_steps(self) -> int:
        return int(self.episode_ends[-1])

    @property
    def num_tasks(self) -> int:
        return len(self.tasks)

    def __getitem__(self, key: str):
        if key not in self.keys:
            raise StoreKeyError(f"{self.path}: no per-step key {key!r}; available: {self.keys}")
        derived = self.derived.get(key)
        if derived:
            return _DerivedArray(self._root()[f"data/{derived[0]}"], derived[1])
        return self._root()[f"data/{key}"]

    def array(self, key: str) -> np.ndarray:
        """A per-step key loaded fully into memory (cached)."""
        if key not in self._cache:
            self[key]  # a KeyError naming the available keys
            derived = self.derived.get(key)
            if derived:
                self._cache[key] = np.ascontiguousarray(self.array(derived[0])[:, list(derived[1])])
            else:
                self._cache[key] = self._read(f"data/{key}")
        return self._cache[key]

    def column(self, name: str) -> np.ndarray:
        """A column of the episode table, shape (E,) (read once; do not modify it)."""
        key = f"meta/{name}"
        if key not in self._cache:
            try:
                self._cache[key] = self._read(key)
            except KeyError:
                raise StoreKeyError(f"{self.path}: no episode column {name!r}") from None
        return self._cache[key]

    def episode_slice(self, index: int) -> slice:
        if not 0 <= index < self.num_episodes:
            raise EpisodeIndexError(f"{self.path}: episode {index} out of range (the store has {self.num_episodes})")
        return slice(int(self.episode_starts[index]), int(self.episode_ends[index]))

    def episode(self, index: int, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """All per-step arrays of one episode."""
        sl = self.episode_slice(index)
        keys = list(keys or self.keys)
        for k in keys:
            self[k]  # a KeyError naming the available keys
        derived = self.derived
        sources = {derived[k][0] if k in derived else k for k in keys}
        stored = {k: self._read(f"data/{k}", sl) for k in sources}
        return {k: stored[derived[k][0]][:, list(derived[k][1])] if k in derived else stored[k] for k in keys}

    def task_episodes(self) -> list[np.ndarray]:
        """For each task index, the indices of its episodes."""
        task_index = self.column("task_index")
        return [np.flatnonzero(task_index == t) for t in range(self.num_tasks)]

    @property
    def task_keys(self) -> list[str]:
        """The ragged per-task arrays' keys (e.g. a drawing's strokes)."""
        root = self._root()
        return sorted(k for k in root["tasks"].array_keys() if not k.endswith("__ends")) if "tasks" in root else []

    def task_array(self, key: str, task_index: int) -> np.ndarray:
        """The ragged per-task array `key` of one task."""
        ends = self._read(f"tasks/{key}__ends")
        start = 0 if task_index == 0 else int(ends[task_index - 1])
        return self._read(f"tasks/{key}", slice(start, int(ends[task_index])))

    def fingerprint(self) -> str:
        """SHA-256 of the store's content: every file's relative path and bytes, except that the header's creation
        time is left out (so a store generated again from the same input has the same fingerprint). Cached."""
        if "_fingerprint" not in self.__dict__:
            digest = hashlib.sha256()
            header = {k: v for k, v in self.attrs.items() if k != "created"}
            digest.update(json.dumps(header, sort_keys=True).encode())
            for file in sorted(p for p in self.path.rglob("*") if p.is_file() and p != self.path / "zarr.json"):
                digest.update(str(file.relative_to(self.path)).encode() + b"\0")
                digest.update(file.read_bytes())
            self._fingerprint = digest.hexdigest()
        return self._fingerprint

    def disk_bytes(self) -> int:
        return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())

    def __repr__(self) -> str:
        return (
            f"EpisodeStore({str(self.path)!r}, benchmark={self.benchmark!r}, tasks={self.num_tasks}, "
            f"episodes={self.num_episodes}, steps={self.num_steps})"
        )


def stored_with(path: str | Path, cfg: Any) -> EpisodeStore | None:
    """The store at `path` if it loads and was generated from exactly the data config `cfg` (a dataclass), else
    None: how scripts and named task sets reuse finished data."""
    try:
        store = EpisodeStore(path)
    except (StoreError, ValueError):
        return None
    same = json.loads(json.dumps(store.config)) == json.loads(json.dumps(to_dict(cfg)))
    return store if same else None


def merge_stores(paths: Iterable[str | Path], out: str | Path, overwrite: bool = False) -> EpisodeStore:
    """One store of every episode of the stores at `paths` (of one benchmark, with the same per-step keys), written
    atomically to `out`: e.g. pieces generated on several machines, or demonstrations of a few tasks added later.
    A task in several stores (the same id) becomes one task with all their episodes; its instruction, info and
    per-task arrays must agree. The merged header keeps the first store's generation config and lists every
    source (path, fingerprint, config) under ``merged_from``; the statistics are those of the merged episodes."""
    stores = [EpisodeStore(p) for p in paths]
    if len(stores) < 2:
        raise StoreError("merging needs at least two stores")
    first = stores[0]
    task_keys = first.task_keys
    for s in stores[1:]:
        if s.benchmark != first.benchmark:
            raise StoreError(
                f"{s.path} holds {s.benchmark} data and {first.path} {first.benchmark} data; merge stores of one "
                "benchmark"
            )
        if s._stored_keys != first._stored_keys:
            raise StoreError(f"{s.path} stores keys {s._stored_keys}, {first.path} {first._stored_keys}")
        if s.task_keys != task_keys:
            raise StoreError(f"{s.path} has per-task arrays {s.task_keys}, {first.path} {task_keys}")
    with EpisodeWriter(out, benchmark=first.benchmark, config=first.config, overwrite=overwrite) as writer:
        merged: dict[str, tuple[int, dict, dict]] = {}  # task id -> (merged index, task entry, per-task arrays)
        for s in stores:
            columns = [k for k in s._root()["meta"].array_keys() if k not in ("episode_ends", "task_index")]
            remap = []
            for t, task in enumerate(s.tasks):
                arrays = {k: s.task_array(k, t) for k in task_keys}  # the same in every store (checked above)
                if task["id"] not in merged:
                    index = writer.add_task(task["id"], task["info"], instruction=task["instruction"], **arrays)
                    merged[task["id"]] = (index, task, arrays)
                index, known, known_arrays = merged[task["id"]]
                if known != task or any(not np.array_equal(known_arrays[k], v) for k, v in arrays.items()):
                    raise StoreError(f"task {task['id']!r} differs between the stores (info, instruction or arrays)")
                remap.append(index)
            task_index = s.column("task_index")
            for e in range(s.num_episodes):
                extra = {k: s.column(k)[e] for k in columns}  # a scalar, or an array (a goal image)
                writer.add_episode(s.episode(e, s._stored_keys), remap[int(task_index[e])], **extra)
        writer.root.attrs["merged_from"] = [
            {"path": str(s.path), "fingerprint": s.fingerprint(), "config": s.config} for s in stores
        ]
    return EpisodeStore(out)
