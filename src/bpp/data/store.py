"""The episode store: one on-disk format for every benchmark.

Layout (a zarr v3 directory)::

    <name>.zarr/
      zarr.json          attributes: format, version, complete, benchmark, config, tasks, stats, created, arrays,
                         digest; tasks is the task table: one {"id", "instruction", "info"} per task
      data/<key>         (N, ...) per-step arrays, episodes concatenated in time, chunked and zstd-compressed
      meta/episode_ends  (E,) int64, exclusive end step of each episode
      meta/<column>      (E,) the episode table: task_index and any per-episode parameters
      tasks/<key>        ragged per-task arrays (e.g. a task's waypoints), with tasks/<key>__ends (K,)

A benchmark may also declare *derived* per-step keys (:attr:`bpp.core.contract.Benchmark.derived_keys`):
chosen features of a stored key, read and normalised like a stored key but never written. Whoever opens a store
passes them (:func:`bpp.core.registry.open_store` passes those of the benchmark the store names), and a pickled store
carries them, so every process that uses it sees the same keys.

Writing is atomic: everything goes into a hidden ``.<name>.partial-<id>`` sibling, ``complete`` is set last,
and only then is the folder renamed into place — an interrupted generation never leaves a store that loads
as complete. A writer owns its destination from start to finish: it holds a lock on the hidden ``.<name>.lock``
sibling, so a second writer of the same path is refused when it starts, and the rename into place never replaces a
store that another writer put there meanwhile unless the writer was asked to overwrite. Reading is safe from many
data-loader processes: the store is read-only once written, and each process opens its own handles lazily (a pickled
store carries only its path).

Every read is verified (version 2). Each chunk of every array ends with a crc32c checksum of its compressed bytes
(zarr's ``crc32c`` codec, after zstd), and every chunk is written, even one that holds only zeros; the reader refuses a
chunk that is missing or fails its checksum, naming the array and the chunk, where zarr alone would read the array's
fill value or decode changed bytes. The header records the SHA-256 of each array's metadata (``arrays``) and of
itself (``digest``), checked when the store is opened, so that changed statistics, tasks, shapes or a deleted array
are refused too.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import functools
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bpp.errors import UserError
from bpp.utils import naming, read_json, to_dict

try:
    import fcntl
except ImportError:  # not POSIX: writers are kept apart by the check at the rename alone
    fcntl = None

try:  # the package zarr's own crc32c codec uses: google-crc32c since zarr 3.1, crc32c before
    from google_crc32c import value as _crc32c
except ModuleNotFoundError:
    from crc32c import crc32c as _crc32c

FORMAT = "bpp-episodes"
VERSION = 2
"""1: the first format. 2: every chunk carries a crc32c checksum and is written even if it holds only zeros; the
header records digests of itself and of each array's metadata."""
ZARR_FORMAT = 3

_CHUNK_KEY = re.compile(r"(?P<array>.+)/c(?P<index>(?:/\d+)*)")
"""A chunk's key in zarr v3's default chunk key encoding: ``data/action/c/3/0`` is chunk (3, 0) of data/action."""
_ARRAY_NAME = re.compile(r"(?:data|meta|tasks)(?:/(?!\.\.?(?:/|$))[^/\\]+)+")
"""The name of an array a store may record: under data/, meta/ or tasks/, with no empty, ``.`` or ``..`` part."""


class StoreError(UserError):
    """A store is missing, incomplete, of another format/version, or used wrongly."""


class StoreKeyError(StoreError, KeyError):
    """A per-step key or episode column the store does not have (a KeyError too, for callers that look one up)."""

    __str__ = Exception.__str__  # the message as written, not KeyError's quoted form


class EpisodeIndexError(StoreError, IndexError):
    """An episode index outside the store."""


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


# ------------------------------------------------------------------ integrity
def _checksum_matches(data: np.ndarray) -> bool:
    """Whether a chunk's stored bytes (uint8) end with the crc32c of the bytes before, as zarr's crc32c codec writes
    it (4 bytes, little-endian)."""
    return len(data) >= 4 and _crc32c(data[:-4]) == int.from_bytes(data[-4:].tobytes(), "little")


def _checked_chunk(root, key: str, value, whole: bool):
    """`value`, what the store at `root` holds under `key` (zarr's Buffer, or None), if `key` is not a chunk's or the
    chunk is there and, if `whole`, matches its checksum; else a StoreError naming the store, the array and the
    chunk."""
    chunk = _CHUNK_KEY.fullmatch(key)
    if chunk is None:  # metadata, or a key zarr probes for
        return value
    if value is None:
        problem = "is missing"
    elif whole and not _checksum_matches(value.as_numpy_array()):
        problem = "fails its checksum"
    else:
        return value
    index = tuple(int(i) for i in chunk["index"].split("/")[1:])
    raise StoreError(
        f"{root}: damaged store, cannot read {chunk['array']}: its chunk {index} ({key}) {problem}; generate it again"
    )


@functools.cache
def _checked_store_class() -> type:
    """A read-only zarr LocalStore that refuses a chunk that is missing or fails its crc32c checksum with a StoreError
    naming the store, the array and the chunk: every read of an array goes through it, whoever reads."""
    # zarr: a third of a second to import, when a store is read or written
    from zarr.storage import LocalStore

    class CheckedStore(LocalStore):
        async def get(self, key, prototype=None, byte_range=None):
            value = await super().get(key, prototype, byte_range)
            return _checked_chunk(self.root, key, value, byte_range is None)

        def get_sync(self, key, *, prototype=None, byte_range=None):  # zarr >= 3.1's synchronous reads
            value = super().get_sync(key, prototype=prototype, byte_range=byte_range)
            return _checked_chunk(self.root, key, value, byte_range is None)

    return CheckedStore


def _array_settings() -> dict:
    """How every array of a store is written: zstd, then a crc32c checksum of the compressed bytes, on each chunk;
    and every chunk written, even one that holds only zeros (zarr skips those by default and reads the fill value in
    their place), so that a missing chunk is damage, never data."""
    # zarr: a third of a second to import, when a store is read or written
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return {"compressors": (ZstdCodec(level=5), Crc32cCodec()), "config": {"write_empty_chunks": True}}


def _header_digest(attrs: dict) -> str:
    """SHA-256 of a store's header attributes other than the digest itself, as parsed from its zarr.json."""
    content = {k: v for k, v in attrs.items() if k != "digest"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def _metadata_digest(path: Path, name: str) -> str | None:
    """SHA-256 of the metadata file of array `name` of the store at `path` (None if there is none)."""
    try:
        return hashlib.sha256((path / name / "zarr.json").read_bytes()).hexdigest()
    except (FileNotFoundError, NotADirectoryError):
        return None


def read_header(path: str | Path) -> dict:
    """The header attributes of the episode store at `path`, checked: a zarr v3 group, of this format and version,
    complete, with the header and every array's metadata matching their digests. Reads only metadata files; a
    StoreError says what is wrong, by the format marker and version first."""
    path = Path(path)
    if not path.exists():
        raise StoreError(f"{path}: no such store")
    if not (path / "zarr.json").is_file():
        if (path / ".zgroup").is_file() or (path / ".zarray").is_file():
            raise StoreError(f"{path}: a zarr format 2 folder, not an episode store (zarr format {ZARR_FORMAT})")
        raise StoreError(f"{path}: not an episode store (no zarr.json)")
    try:
        doc = read_json(path / "zarr.json", "store header")
    except UserError as err:
        raise StoreError(f"{path}: damaged store header ({err}); generate it again") from None
    if not isinstance(doc, dict):
        raise StoreError(f"{path}: damaged store header (not a zarr metadata document); generate it again")
    if doc.get("zarr_format") != ZARR_FORMAT or doc.get("node_type") != "group":
        what = f"zarr format {doc.get('zarr_format')!r}" + (
            f", a zarr {doc.get('node_type')}" if doc.get("node_type") != "group" else ""
        )
        raise StoreError(
            f"{path}: not an episode store ({what}; an episode store is a zarr format {ZARR_FORMAT} group)"
        )
    attrs = doc.get("attributes", {})
    if not isinstance(attrs, dict):
        raise StoreError(f"{path}: damaged store header (its attributes are not a mapping); generate it again")
    if attrs.get("format") != FORMAT:
        raise StoreError(f"{path}: not an episode store (format {attrs.get('format')!r}, expected {FORMAT!r})")
    version = attrs.get("version")
    if version != VERSION:
        if isinstance(version, int) and not isinstance(version, bool) and 0 < version < VERSION:
            raise StoreError(
                f"{path}: store version {version}, written by an older bpp; this bpp reads version {VERSION} "
                "(checksummed chunks): generate it again"
            )
        raise StoreError(f"{path}: store version {version!r}, this bpp reads version {VERSION}")
    if not attrs.get("complete"):
        raise StoreError(f"{path}: incomplete store (its generation was interrupted); generate it again")
    if attrs.get("digest") != _header_digest(attrs):
        raise StoreError(f"{path}: damaged store header (it does not match its digest); generate it again")
    arrays = attrs.get("arrays")
    if not isinstance(arrays, dict) or not all(isinstance(n, str) and _ARRAY_NAME.fullmatch(n) for n in arrays):
        raise StoreError(f"{path}: damaged store header (no valid table of arrays); generate it again")
    for name, digest in arrays.items():
        found = _metadata_digest(path, name)
        if found is None:
            raise StoreError(f"{path}: damaged store (no {name}); generate it again")
        if found != digest:
            raise StoreError(
                f"{path}: damaged store, the metadata of {name} ({name}/zarr.json) does not match its digest; "
                "generate it again"
            )
    return attrs


def _enclosing_store(path: Path) -> Path | None:
    """The episode store (complete or not) that `path` would lie inside, if any."""
    return next((parent for parent in path.resolve().parents if _is_store(parent)), None)


class _DestinationLock:
    """A writer's exclusive hold on a store path: an advisory lock (flock) on the hidden sibling ``.<name>.lock``,
    which holds the writer's process id. The kernel drops it when that process ends, however it ends; the file is
    removed on release."""

    def __init__(self, path: Path):
        self.file = path.parent / f".{path.name}.lock"
        self.handle = None
        if fcntl is None:
            return
        while True:
            try:
                handle = open(self.file, "a+")  # noqa: SIM115 - held open until release
            except OSError as err:
                raise StoreError(f"{path}: cannot write there ({err.strerror}: {self.file})") from None
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                handle.seek(0)
                holder = handle.read().strip()[:100]
                handle.close()
                if err.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise StoreError(
                        f"{path} is being written by another writer ({holder or 'another process'}); wait for it to "
                        "finish, or choose another path"
                    ) from None
                return  # a file system without locks: the check at the rename remains
            try:  # the file may have been removed by a writer that finished meanwhile: then lock the new one
                same = os.stat(self.file).st_ino == os.fstat(handle.fileno()).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            handle.close()
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()}")
        handle.flush()
        self.handle = handle

    def release(self) -> None:
        if self.handle is not None:
            with contextlib.suppress(FileNotFoundError):
                self.file.unlink()  # while still locked, so that no other writer holds a lock on a removed file
            self.handle.close()
            self.handle = None


@contextlib.contextmanager
def destination_lock(path: str | Path) -> Iterator[None]:
    """Hold, for the block, the lock a writer of `path` holds (a StoreError at once if another writer holds it): for
    work that fills `path` over longer than one writer lives, e.g. a journal of finished tasks that a killed
    generation resumes from."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = _DestinationLock(path)
    try:
        yield
    finally:
        lock.release()


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
        enclosing = _enclosing_store(self.path)
        if enclosing is not None:
            raise StoreError(
                f"{self.path} is inside the episode store {enclosing}, which would change it; choose a path outside it"
            )
        self._check_destination(overwrite)  # before anything is written, so that a refusal changes nothing
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = _DestinationLock(self.path)
        self.tmp = self.path.parent / f".{self.path.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
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
        if self.path.exists() and not _is_store(self.path):
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
            name, shape=shape, chunks=chunks, dtype=example.dtype, **_array_settings()
        )

    def _table(self, name: str, data: np.ndarray) -> None:
        """Array `name` holding `data` (an episode table column, a per-task array), chunked as zarr chooses."""
        self._arrays[name] = self.root.create_array(name, data=data, **_array_settings())

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
                    "arrays": {name: _metadata_digest(self.tmp, name) for name in sorted(self._arrays)},
                    "complete": True,
                }
            )
            # The digest of the header as it is on disk, as a reader parses it.
            attrs = read_json(self.tmp / "zarr.json", "store header")["attributes"]
            self.root.attrs["digest"] = _header_digest(attrs)
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
            if not _is_store(self.path):
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
    however it is read (:meth:`array`, :meth:`episode`, the lazy arrays), is checked to be there and to match its
    checksum, or refused with a StoreError naming it.
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
        array if a chunk is missing or corrupt (and the chunk: see :func:`_checked_store_class`). A KeyError if the
        header records no such array."""
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

            store = _checked_store_class()(str(self.path), read_only=True)
            handle = (os.getpid(), zarr.open_group(store=store, mode="r"))
            self._handle = handle
        return handle[1]

    def verify(self) -> int:
        """Read every chunk of every array, each checked as every read checks it (present, matching its checksum);
        returns the number of chunks read. A StoreError names the first damaged one. Reads about 64 MB at a time."""
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
    None: how scripts and named task sets reuse finished data."""
    try:
        store = EpisodeStore(path)
    except (StoreError, ValueError):
        return None
    same = json.loads(json.dumps(store.config)) == json.loads(json.dumps(to_dict(cfg)))
    return store if same else None


def _refuse_overlaps(stores: list[EpisodeStore], out: Path) -> None:
    """Refuse a merge whose inputs include one store twice (by any path to it), or whose output is an input, lies
    inside one or holds one: the first would double every demonstration, the others change an input."""
    for i, store in enumerate(stores):
        for other in stores[:i]:
            if os.path.samefile(store.path, other.path):
                raise StoreError(
                    f"{store.path} is {other.path} given again: a store merged with itself holds each of its "
                    "demonstrations twice"
                )
    target = out.resolve()
    for store in stores:
        source = store.path.resolve()
        if target == source:
            raise StoreError(f"{out}: the merge would be written over its input {store.path}; choose a new path")
        if source in target.parents:
            raise StoreError(f"{out}: the merge would be written inside its input {store.path}; choose a path outside")
        if target in source.parents:
            raise StoreError(f"{out}: the merge would replace a folder holding its input {store.path}")


def _episode_digest(steps: dict[str, np.ndarray]) -> bytes:
    """SHA-256 of an episode's per-step arrays (keys, dtypes, shapes and bytes)."""
    digest = hashlib.sha256()
    for key in sorted(steps):
        value = np.ascontiguousarray(steps[key])
        digest.update(f"{key}\0{value.dtype.str}\0{value.shape}\0".encode())
        digest.update(value.tobytes())
    return digest.digest()


def merge_stores(paths: Iterable[str | Path], out: str | Path, overwrite: bool = False) -> EpisodeStore:
    """One store of every episode of the stores at `paths` (of one benchmark, with the same per-step keys), written
    atomically to `out`: e.g. pieces generated on several machines, or demonstrations of a few tasks added later.
    A task in several stores (the same id) becomes one task with all their episodes; its instruction, info and
    per-task arrays must agree. The merged header keeps the first store's generation config and lists every
    source (path, fingerprint, config) under ``merged_from``; the statistics are those of the merged episodes.

    Refused: a store given twice, an episode that two of the stores hold (a store merged with a copy of itself, or
    with a merge that includes it: its demonstrations would count twice), and an output that is an input, lies
    inside one or holds one."""
    stores = [EpisodeStore(p) for p in paths]
    if len(stores) < 2:
        raise StoreError("merging needs at least two stores")
    _refuse_overlaps(stores, Path(out))
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
        seen: dict[bytes, tuple[int, int]] = {}  # episode digest -> (store, episode) that first held it
        for n, s in enumerate(stores):
            columns = [k for k in s._names("meta") if k not in ("episode_ends", "task_index")]
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
                steps = s.episode(e, s._stored_keys)
                m, f = seen.setdefault(_episode_digest(steps), (n, e))
                if m != n:
                    raise StoreError(
                        f"episode {e} of {s.path} is episode {f} of {stores[m].path} again: merged, it would count "
                        "twice (is one store a copy of the other, or a merge that includes it?)"
                    )
                extra = {k: s.column(k)[e] for k in columns}  # a scalar, or an array (a goal image)
                writer.add_episode(steps, remap[int(task_index[e])], **extra)
        writer.root.attrs["merged_from"] = [
            {"path": str(s.path), "fingerprint": s.fingerprint(), "config": s.config} for s in stores
        ]
    return EpisodeStore(out)
