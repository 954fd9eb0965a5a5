"""The episode store: one on-disk format for every benchmark.

Layout (a zarr v3 directory)::

    <name>.zarr/
      zarr.json          attributes: format, version, complete, benchmark, config, tasks, stats, created, arrays,
                         chunks, digest; tasks is the task table: one {"id", "instruction", "info"} per task
      data/<key>         (N, ...) per-step arrays, episodes concatenated in time, chunked and zstd-compressed
      meta/episode_ends  (E,) int64, exclusive end step of each episode
      meta/<column>      (E,) the episode table: task_index and any per-episode parameters
      tasks/<key>        ragged per-task arrays (e.g. a task's waypoints), with tasks/<key>__ends (K,)

A benchmark may also declare *derived* per-step keys (:attr:`bpp.core.contract.Benchmark.derived_keys`):
chosen features of a stored key, read and normalised like a stored key but never written. Whoever opens a store
passes them (:func:`bpp.core.registry.open_store` passes those of the benchmark the store names), and a pickled store
carries them, so every process that uses it sees the same keys.

Writing is atomic: everything goes into a hidden ``.<name>.partial-<pid>-<id>`` sibling, ``complete`` is set last,
and only then is the folder renamed into place — an interrupted generation never leaves a store that loads
as complete. A writer owns its destination from start to finish: it holds a lock on the hidden ``.<name>.lock``
sibling, so a second writer of the same path is refused when it starts, and the rename into place never replaces a
store that another writer put there meanwhile unless the writer was asked to overwrite. Reading is safe from many
data-loader processes: the store is read-only once written, and each process opens its own handles lazily (a pickled
store carries only its path).

Every read is verified (:mod:`bpp.data.integrity`): opening a store checks its header and each array's metadata against
their digests, and every chunk read must be there, match the checksum it carries, and carry the checksum the header
records for its key; a StoreError names the store, the array and the chunk. :mod:`bpp.data.merge` merges stores.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bpp.data.arrays import first_non_finite
from bpp.data.destination import DestinationLock, enclosing_store, partial_path, remove_stale_partials
from bpp.data.integrity import (
    FORMAT,
    VERSION,
    EpisodeIndexError,
    StoreBusy,
    StoreError,
    StoreKeyError,
    array_settings,
    checked_store_class,
    chunk_manifest,
    header_digest,
    is_store,
    metadata_digest,
    read_header,
)
from bpp.utils import naming, read_json, to_dict

DerivedKeys = Mapping[str, tuple[str, tuple[int, ...]]]
"""Derived per-step keys: key -> (stored source key, feature indices), as a benchmark declares them."""


def with_derived(derived_keys: DerivedKeys, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`obs` (per-step arrays, features last) plus every key of `derived_keys` whose source it has (the same features
    a store opened with those keys presents)."""
    derived = {
        key: np.asarray(obs[source])[..., list(features)]
        for key, (source, features) in derived_keys.items()
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


def _check_finite(key: str, value: np.ndarray, episode: int) -> None:
    """Refuse a per-step array with a NaN or an infinity: a store holds finite numbers only, so that no statistic,
    normaliser or trained weight downstream of it turns into NaN (every writer passes this door: generators,
    importers, merges)."""
    found = first_non_finite(value)
    if found is None:
        return
    step, item = found
    raise StoreError(
        f"episode {episode}: {key!r} holds {value.reshape(len(value), -1)[step, item]} at step {step} (item {item}); "
        "a store keeps finite numbers only"
    )


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

    The writer owns `path` from construction to :meth:`close` or :meth:`abort`: a second writer of the same path is
    refused while it runs, and without `overwrite` a store that appears at `path` meanwhile is never replaced.

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
        # zarr: a third of a second to import, when a store is read or written
        import zarr

        self.path = Path(path)
        self._closed = False
        self._lock = None
        enclosing = enclosing_store(self.path)
        if enclosing is not None:
            raise StoreError(
                f"{self.path} is inside the episode store {enclosing}, which would change it; choose a path outside it"
            )
        self._check_destination(overwrite)  # before anything is written, so that a refusal changes nothing
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = DestinationLock(self.path)
        self.tmp = partial_path(self.path)
        try:
            self._check_destination(overwrite)  # again, now that no other writer can change it
            remove_stale_partials(self.path)
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
        except BaseException as err:  # a full disk, Ctrl-C: nothing stays behind
            self.abort()
            if isinstance(err, OSError):
                raise naming(err, self.path) from None
            raise
        self.overwrite = overwrite
        self.chunk_steps = chunk_steps
        self.stats_keys = None if stats_keys is None else set(stats_keys)
        self._arrays: dict[str, Any] = {}  # name -> the zarr array written through (it writes every chunk)
        self._buffer: dict[str, list[np.ndarray]] = {}
        self._buffered = 0
        self._step_spec: dict[str, tuple[tuple[int, ...], np.dtype]] | None = None
        self._stats: dict[str, _RunningStats] = {}
        self._ends: list[int] = []
        self._columns: dict[str, list] = {}
        self._tasks: list[dict] = []
        self._task_ragged: dict[str, list[np.ndarray]] = {}

    def _check_destination(self, overwrite: bool) -> None:
        if os.path.lexists(self.path) and not overwrite:
            raise StoreError(f"{self.path} already exists; pass overwrite=True (CLI: --overwrite) to replace it")
        if self.path.exists() and not is_store(self.path):
            raise StoreError(
                f"{self.path} exists and is not an episode store; only a store is ever replaced (delete it yourself "
                "if you mean to)"
            )

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
            _check_finite(key, np.asarray(value), len(self._ends))
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
        try:
            for key, parts in self._buffer.items():
                data = np.concatenate(parts)
                name = f"data/{key}"
                if name not in self._arrays:
                    self._create(name, data, self.chunk_steps)
                self._arrays[name].append(data)
        except OSError as err:  # a full disk: zarr names no file; name the store
            raise naming(err, self.path) from None
        self._buffer = {}
        self._buffered = 0

    def _create(self, name: str, example: np.ndarray, chunk_len: int):
        item_bytes = max(int(np.prod(example.shape[1:])) * example.dtype.itemsize, 1)
        rows = int(max(1, min(chunk_len, (8 << 20) // item_bytes)))  # chunks of at most ~8 MB
        shape, chunks = (0, *example.shape[1:]), (rows, *example.shape[1:])
        self._arrays[name] = self.root.create_array(
            name, shape=shape, chunks=chunks, dtype=example.dtype, **array_settings()
        )

    def _table(self, name: str, data: np.ndarray) -> None:
        """Array `name` holding `data` (an episode table column, a per-task array), chunked as zarr chooses."""
        self._arrays[name] = self.root.create_array(name, data=data, **array_settings())

    # --------------------------------------------------------------- finishing
    def close(self) -> EpisodeStore:
        """Write tables and statistics, mark complete, and move the store into place. On any failure the store is
        discarded, as by :meth:`abort`."""
        if self._closed:
            raise StoreError("writer already closed")
        try:
            if not self._ends:
                raise StoreError(f"{self.path}: no episodes were added; refusing to write an empty store")
            self._flush()
            self._table("meta/episode_ends", np.asarray(self._ends, dtype=np.int64))
            for key, values in self._columns.items():
                self._table(f"meta/{key}", np.asarray(values))
            for key, parts in self._task_ragged.items():
                self._table(f"tasks/{key}", np.concatenate(parts))
                self._table(f"tasks/{key}__ends", np.cumsum([len(p) for p in parts]).astype(np.int64))
            self.root.attrs.update(
                {
                    "tasks": self._tasks,
                    "stats": {k: s.result() for k, s in self._stats.items()},
                    "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "arrays": {name: metadata_digest(self.tmp, name) for name in sorted(self._arrays)},
                    "chunks": chunk_manifest(self.tmp, sorted(self._arrays)),
                    "complete": True,
                }
            )
            # The digest of the header as it is on disk, as a reader parses it.
            attrs = read_json(self.tmp / "zarr.json", "store header")["attributes"]
            self.root.attrs["digest"] = header_digest(attrs)
            self._install()
        except OSError as err:
            self.abort()
            raise naming(err, self.path) from None
        except BaseException:
            self.abort()
            raise
        self._closed = True
        self._lock.release()
        return EpisodeStore(self.path)

    def _install(self) -> None:
        """Rename the finished store into place: replacing an existing store only if asked to overwrite, and never a
        store that another writer (one that did not take the lock: another machine, another program) put there
        since this one started, unless asked to overwrite."""
        if os.path.lexists(self.path) and not self.overwrite:
            raise StoreError(
                f"{self.path} appeared while this store was being written (another writer?); it was left as it is "
                "and this store discarded: choose another path, or pass overwrite=True (CLI: --overwrite)"
            )
        old = None
        if os.path.lexists(self.path):
            if not is_store(self.path):
                raise StoreError(f"{self.path} is no longer an episode store; only a store is ever replaced")
            old = self.path.parent / f".{self.path.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(self.path, old)
        try:
            os.rename(self.tmp, self.path)  # refused by the OS if a non-empty folder or a file is there
        except OSError as err:
            if old is not None:
                with contextlib.suppress(OSError):
                    os.rename(old, self.path)
            if os.path.lexists(self.path):
                raise StoreError(
                    f"{self.path} appeared while this store was being written (another writer?); it was left as it "
                    "is and this store discarded"
                ) from None
            raise StoreError(f"{self.path}: cannot move the finished store into place ({err})") from None
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        """Discard everything written so far."""
        self._closed = True
        shutil.rmtree(self.tmp, ignore_errors=True)
        if self._lock is not None:
            self._lock.release()

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
    Opening checks the header and each array's metadata against their digests (:func:`read_header`); every chunk,
    however it is read (:meth:`array`, :meth:`episode`, the lazy arrays), is checked to be there, to match its
    checksum and to be the chunk the header records under its key, or refused with a StoreError naming it
    (:func:`bpp.data.integrity.chunk_problem`).
    """

    def __init__(self, path: str | Path, derived_keys: DerivedKeys | None = None):
        self.path = Path(path)
        attrs = read_header(self.path)
        self.attrs = attrs
        try:
            self.benchmark: str = attrs["benchmark"]
            self.config: dict = attrs.get("config", {})
            self.tasks: list[dict] = attrs["tasks"]
            self._stored_stats: dict[str, dict[str, list[float]]] = attrs["stats"]
        except KeyError as err:
            raise StoreError(f"{self.path}: damaged store header (no {err} entry); generate it again") from None
        self._arrays: frozenset[str] = frozenset(attrs["arrays"])
        self._manifest: dict[str, int] | None = attrs.get("chunks") if attrs["version"] >= 3 else None
        self._cache: dict[str, np.ndarray] = {}
        try:
            self.episode_ends = self._read("meta/episode_ends")
        except KeyError:
            raise StoreError(f"{self.path}: damaged store (no meta/episode_ends); generate it again") from None
        self.episode_starts = np.concatenate([[0], self.episode_ends[:-1]])
        self._stored_keys: list[str] = self._names("data")
        self.derived: dict[str, tuple[str, tuple[int, ...]]] = {
            key: (source, tuple(features))
            for key, (source, features) in (derived_keys or {}).items()
            if source in self._stored_keys and key not in self._stored_keys
        }
        """Its derived keys: key -> (stored source key, feature indices), those of `derived_keys` whose source it
        stores (:attr:`bpp.core.contract.Benchmark.derived_keys`)."""
        if len(self.episode_ends) == 0 or np.any(np.diff(self.episode_ends) <= 0) or self.episode_ends[0] <= 0:
            raise StoreError(f"{self.path}: damaged store (meta/episode_ends is not increasing); generate it again")

    def _names(self, group: str) -> list[str]:
        """The arrays of `group` (data, meta or tasks) the header records, by their names inside it, sorted."""
        return sorted(name[len(group) + 1 :] for name in self._arrays if name.startswith(f"{group}/"))

    def _read(self, name: str, selection: slice = slice(None)) -> np.ndarray:
        """Array `name` of the store (or a slice of its first axis), with a StoreError naming the store and the
        array if a chunk is missing, corrupt or another's (and the chunk: see
        :func:`~bpp.data.integrity.checked_store_class`). A KeyError if the header records no such array."""
        if name not in self._arrays:
            raise KeyError(name)
        try:
            return np.asarray(self._root()[name][selection])
        except StoreError:
            raise
        except Exception as err:  # noqa: BLE001 - zarr and its codecs raise their own errors
            raise StoreError(
                f"{self.path}: damaged store, cannot read {name} ({type(err).__name__}: {err}); generate it again"
            ) from None

    def _root(self):
        # One handle per process: handles are not shared across fork/spawn (see __getstate__).
        handle = getattr(self, "_handle", None)
        if handle is None or handle[0] != os.getpid():
            # zarr: a third of a second to import, when a store is read or written
            import zarr

            store = checked_store_class()(str(self.path), read_only=True, manifest=self._manifest)
            handle = (os.getpid(), zarr.open_group(store=store, mode="r"))
            self._handle = handle
        return handle[1]

    @property
    def chunks_recorded(self) -> bool:
        """Whether the header records the checksum of each chunk by its key (version 3 on), so that a chunk of another
        store, or from elsewhere in this one, is refused; a version 2 store's chunks are checked against the checksums
        they carry alone."""
        return self._manifest is not None

    def verify(self) -> int:
        """Read every chunk of every array, each checked as every read checks it (present, matching its checksum, the
        chunk the header records under its key); returns the number of chunks read. A StoreError names the first
        damaged one. Reads about 64 MB at a time."""
        chunks = 0
        for name in sorted(self._arrays):
            array = self._root()[name]
            if array.ndim == 0:
                self._read(name, ())
            else:
                row_bytes = max(int(np.prod(array.shape[1:])) * array.dtype.itemsize, 1)
                rows = array.chunks[0] * max(1, (64 << 20) // (array.chunks[0] * row_bytes))
                for start in range(0, array.shape[0], rows):
                    self._read(name, slice(start, start + rows))
            chunks += array.nchunks
        return chunks

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_handle", None)
        state["_cache"] = {}
        return state

    # ---------------------------------------------------------------- queries
    @property
    def stored_keys(self) -> list[str]:
        """Per-step keys the store holds (its derived keys left out)."""
        return list(self._stored_keys)

    @property
    def columns(self) -> list[str]:
        """The episode table's columns: task_index and any per-episode parameters."""
        return [name for name in self._names("meta") if name != "episode_ends"]

    def spec(self, name: str) -> tuple[tuple[int, ...], np.dtype]:
        """The shape past the first axis and the dtype of array `name` (``data/action``, ``meta/angle``,
        ``tasks/strokes``), from its metadata alone."""
        array = self._root()[name]
        return tuple(array.shape[1:]), array.dtype

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
        return [k for k in self._names("tasks") if not k.endswith("__ends")]

    def task_array(self, key: str, task_index: int) -> np.ndarray:
        """The ragged per-task array `key` of one task."""
        ends = self._read(f"tasks/{key}__ends")
        start = 0 if task_index == 0 else int(ends[task_index - 1])
        return self._read(f"tasks/{key}", slice(start, int(ends[task_index])))

    def fingerprint(self) -> str:
        """SHA-256 of the store's content: every file's relative path and bytes, except that the header's creation
        time, its ``timing`` (how fast a generator made it) and its digest, which covers them, are left out (so a
        store generated again from the same input, on any machine, has the same fingerprint). Cached."""
        if "_fingerprint" not in self.__dict__:
            digest = hashlib.sha256()
            header = {k: v for k, v in self.attrs.items() if k not in ("created", "timing", "digest")}
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
    None: how scripts and named task sets reuse finished data. A merge is not generated from its config (it keeps its
    first store's: :func:`bpp.data.merge.merge_stores`), so it is never one."""
    try:
        store = EpisodeStore(path)
    except (StoreError, ValueError):
        return None
    generated = "merged_from" not in store.attrs
    same = generated and json.loads(json.dumps(store.config)) == json.loads(json.dumps(to_dict(cfg)))
    return store if same else None


def stored_or_made(
    path: str | Path, make: Callable[[Path], EpisodeStore], cfg: Any = None, poll_s: float = 1.0
) -> EpisodeStore:
    """The finished store at `path` (with `cfg`, only one generated from exactly that config: :func:`stored_with`),
    else the one `make(path)` writes there. While another process writes `path` (two runs that need the same missing
    data start at once), this waits for it and takes its store instead of failing."""
    path, waiting = Path(path), False
    while True:
        if cfg is not None:
            store = stored_with(path, cfg)
        else:
            try:
                store = EpisodeStore(path)
            except (StoreError, ValueError):
                store = None
        if store is not None:
            return store
        try:
            return make(path)
        except StoreBusy:
            if not waiting:
                print(f"[store] {path} is being written by another process; waiting for it", flush=True)
                waiting = True
            time.sleep(poll_s)
