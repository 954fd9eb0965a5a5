"""Small helpers: dataclass <-> JSON, tensors <-> devices, atomic file writes, file names from ids."""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import hashlib
import json
import math
import os
import re
import shutil
import signal
import sys
import threading
import typing
import uuid
from collections.abc import Iterator
from multiprocessing import context as mp_context
from multiprocessing import resource_tracker
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

import numpy as np

from bpp.errors import UserError


def to_dict(obj: Any) -> Any:
    """A (nested) dataclass as plain JSON-able data."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (nested, frozen) dataclass from :func:`to_dict` output (a saved config); unknown keys are a
    :class:`~bpp.errors.UserError`."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise UserError(f"{cls.__name__}: unknown fields {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _convert(hints[name], value)
    return cls(**kwargs)


def _convert(tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        return from_dict(tp, value)
    if origin is tuple and isinstance(value, list):
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        return tuple(_convert(inner, v) for v in value)
    if tp is Path or (origin is typing.Union and Path in typing.get_args(tp) and isinstance(value, str)):
        return Path(value)
    return value


def check_fields(obj: Any, *rules: tuple[str, bool, str]) -> None:
    """Range checks for a config's ``__post_init__``: each rule is (field, whether it holds, what the field must
    be; a dotted name reaches into a nested config). Raises a UserError naming the first field that fails, what it must
    be and the value given. Write rules as positive conditions (``x > 0``), so a NaN fails them."""
    for name, ok, expected in rules:
        if not ok:
            value = functools.reduce(getattr, name.split("."), obj)
            raise UserError(f"{name} must be {expected}, got {value!r}")


_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


@contextlib.contextmanager
def worker_pool(context, workers: int, initializer=None, initargs: tuple = ()) -> Iterator[Any]:
    """A pool of `workers` processes (multiprocessing's fork or spawn `context`) for the block, terminated when it
    ends however it ends (an error, Ctrl-C, SIGTERM). The workers leave interrupts to this process, which reports them
    and stops the pool: they ignore Ctrl-C, which a terminal sends to every process of the command, and SIGTERM, which
    a job scheduler or systemd may send to all of them too, from their start (a spawned worker imports torch for
    seconds before `initializer` runs), so that none prints a traceback of its own, and none dies halfway through
    passing a task or a result, which would leave the pool's teardown waiting for ever. The pool stops them with
    SIGKILL instead. On Linux they also die with this process when nothing stops them (a library caller killed by
    SIGTERM's default, or by SIGKILL). ``initializer(*initargs)`` then runs in each."""
    method = context.get_start_method()
    assert method in _KILLING_CONTEXTS, f"worker_pool supports fork and spawn, not {method}"
    pool = None
    try:
        with _held_for_workers():
            pool = _KILLING_CONTEXTS[method]().Pool(workers, _start_worker, (initializer, initargs, os.getpid()))
        yield pool
    finally:
        if pool is not None:
            pool.terminate()


def _start_worker(initializer, initargs: tuple, parent: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)  # what came meanwhile is dropped
    _die_with(parent)
    if initializer is not None:
        initializer(*initargs)


def _die_with(parent: int) -> None:
    """Have Linux kill this process (SIGKILL) when `parent`, which started it, ends; elsewhere, nothing."""
    if not sys.platform.startswith("linux"):
        return

    pr_set_pdeathsig = 1
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    if os.getppid() != parent:  # it ended before the request was in place
        os._exit(1)


class _KilledSpawnProcess(mp_context.SpawnProcess):
    """A spawned pool worker, which ignores SIGTERM: Pool.terminate, once the pool's queues are done with, kills it
    (SIGKILL) where it would send SIGTERM. At module level: a spawned worker unpickles its class."""

    def terminate(self) -> None:
        self.kill()


class _KillingSpawnContext(mp_context.SpawnContext):
    Process = _KilledSpawnProcess


_KILLING_CONTEXTS: dict[str, type] = {"spawn": _KillingSpawnContext}

if hasattr(mp_context, "ForkContext"):  # POSIX

    class _KilledForkProcess(mp_context.ForkProcess):
        """A forked pool worker, killed as :class:`_KilledSpawnProcess` is."""

        def terminate(self) -> None:
            self.kill()

    class _KillingForkContext(mp_context.ForkContext):
        Process = _KilledForkProcess

    _KILLING_CONTEXTS["fork"] = _KillingForkContext


@contextlib.contextmanager
def _held_for_workers() -> Iterator[None]:
    """Ctrl-C and SIGTERM held back while the block starts worker processes. This process takes them when the block
    ends (a spawned pool takes seconds to start: each worker imports its modules first), once its workers exist to be
    stopped; the workers inherit a mask that holds them back until :func:`_start_worker` ignores them."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return

    # Started later, by the first spawned worker, the tracker would release the mask (it holds these signals back
    # only while it starts itself).
    resource_tracker.ensure_running()
    received: list[int] = []
    handlers = {
        signum: signal.signal(signum, lambda signum, frame: received.append(signum))
        for signum in _STOP_SIGNALS
        if signal.getsignal(signum) not in (signal.SIG_IGN, None)
    }
    # The mask is this thread's, which the workers inherit; another thread of this process may still take a signal,
    # which the handlers above then hold back.
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        if received:
            signal.raise_signal(received[0])


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


MAX_JSON_BYTES = 64 << 20
"""JSON files bpp reads (configs, checkpoint state, results, drawing files) are refused above this size."""


def read_json(path: str | Path, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Parse the JSON file `path`, or raise a UserError naming it and `what` it should be: unreadable, over
    `max_bytes`, not UTF-8, not JSON, nested too deeply for the parser (Python's RecursionError), or holding a number
    no float can hold (an integer of more than 300 digits, a decimal that overflows to infinity)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            limit = max_bytes / 2**20
            raise UserError(f"{path}: {size / 2**20:.0f} MiB, more than the {limit:.0f} MiB a {what} may have")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: cannot read the {what} ({err})") from None
    try:
        return json.loads(text, parse_int=_json_int, parse_float=_json_float)
    except json.JSONDecodeError as err:
        raise UserError(f"{path}: the {what} is not valid JSON ({err})") from None
    except _NumberTooLarge as err:
        raise UserError(f"{path}: the {what} holds {err}") from None
    except RecursionError:
        raise UserError(f"{path}: the {what} is nested too deeply to parse") from None


class _NumberTooLarge(ValueError):
    pass


def _json_int(text: str) -> int:
    if len(text.lstrip("-")) > 300:  # past float's range; Python refuses to convert over 4300 digits anyway
        raise _NumberTooLarge(f"an integer of {len(text.lstrip('-'))} digits ({text[:12]}...), too large for a number")
    return int(text)


def _json_float(text: str) -> float:
    value = float(text)
    if math.isinf(value):
        raise _NumberTooLarge(f"the number {text[:24]}{'...' if len(text) > 24 else ''}, which overflows a float")
    return value


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write `data` as JSON to `path`, complete or not at all (:func:`atomic_path`)."""
    text = json.dumps(data, indent=1)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write `text` to `path`, complete or not at all (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def naming(err: OSError, path: str | Path) -> OSError:
    """`err` as an OSError naming `path` ("path: No space left on device"), where the system named no file or a
    temporary one: a full disk or a failed write is reported with the output the user asked for. The same errno, so
    the same subclass (PermissionError, ...)."""
    if err.errno is None or (err.filename is not None and ".partial-" not in str(err.filename)):
        return err
    return OSError(err.errno, err.strerror or os.strerror(err.errno), str(path))


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A hidden temporary sibling of `path` to write a file (or a folder) into, moved onto `path` when the block ends
    and removed if it raises (an error, a full disk, Ctrl-C or SIGTERM): `path` is then complete or as it was, never
    half-written. The temporary name keeps `path`'s suffix, which writers such as matplotlib and imageio go by. An
    OSError names `path` (:func:`naming`)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as err:
        _remove(tmp)
        raise naming(err, path) from None
    except BaseException:
        _remove(tmp)
        raise


_PARTIAL = re.compile(r"\..+\.partial-(?P<pid>[0-9]+)-[0-9a-f]{8}(?:\.[^.]*)?")
"""The name :func:`atomic_path` (and :class:`bpp.data.store.EpisodeWriter`) gives what it writes: the writer's
process id, then a random tag."""


def remove_stale_partials(folder: str | Path) -> list[Path]:
    """Delete what writers killed outright (SIGKILL, a power loss) left half-written in `folder`: the hidden
    temporary files and folders of :func:`atomic_path` whose process no longer runs. Returns them."""
    removed = []
    with contextlib.suppress(OSError):  # a folder not there (yet) holds nothing stale
        for entry in Path(folder).iterdir():
            match = _PARTIAL.fullmatch(entry.name)
            if match and not process_alive(int(match["pid"])):
                _remove(entry)
                removed.append(entry)
    return removed


def journal_folder(out: str | Path, key: Any, create: bool = True) -> Path:
    """The journal folder of a long job writing `out` (``.<out's name>.journal`` beside it), where finished parts are
    kept so that the same job run again after an interruption does only the rest: reused if it was started with the
    same `key` (JSON-able: the job's configuration), else emptied (a note says so); what a writer killed outright left
    half-written in it is removed. With ``create=False`` a folder not there yet is left for the first part to make
    (a job refused before it finishes anything leaves nothing behind)."""
    out = Path(out)
    folder = out.with_name(f".{out.name}.journal")
    key = json.dumps(key, sort_keys=True)
    if folder.exists():
        try:
            same = (folder / "config.json").read_text() == key
        except OSError:
            same = False
        if not same:
            print(f"[journal] discarding {folder}: it was started with another configuration")
            shutil.rmtree(folder)
    if not create and not folder.exists():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    remove_stale_partials(folder)
    (folder / "config.json").write_text(key)
    return folder


def process_alive(pid: int) -> bool:
    """Whether process `pid` runs on this machine (someone else's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_VERBATIM = re.compile(r"[a-z0-9_][a-z0-9._-]{0,99}")
"""Ids kept as they are in file names: at most 100 characters, lowercase, no leading dot (a hidden file, '..') nor
characters a file system or a shell treats specially."""
_HASHED = re.compile(r".*-[0-9a-f]{10}")
"""How a name made by :func:`file_stem` with a hash ends; an id that ends so is hashed too, so none can pose as
another's name."""


def file_stem(text: str) -> str:
    """`text` (a task id) as a part of a file name: one name per text, at most 100 characters.

    `text` itself if it is at most 100 lowercase letters, digits, '-', '_' and '.' (not first nor last), else a
    readable slug of it (other characters as '_', at most 80 of them) plus '-' and 10 hex digits of its SHA-256.
    Distinct texts get distinct names, also on a case-insensitive file system (macOS, Windows), where 'Star' and
    'star' would otherwise share a file; none is hidden, '..', a path or too long for a file system."""
    if _VERBATIM.fullmatch(text) and not text.endswith(".") and not _HASHED.fullmatch(text):
        return text
    slug = re.sub(r"[^A-Za-z0-9._-]", "_", text).strip(".")[:80] or "_"
    return f"{slug}-{hashlib.sha256(text.encode('utf-8', 'surrogatepass')).hexdigest()[:10]}"


def to_torch(batch: Any, device: torch.device | str) -> Any:
    """Nested dicts of numpy arrays / tensors -> tensors on `device` (floats as float32, images kept uint8)."""
    # torch: imported when the command runs, not when the command line starts
    import torch

    if isinstance(batch, dict):
        return {k: to_torch(v, device) for k, v in batch.items()}
    if isinstance(batch, np.ndarray):
        batch = torch.from_numpy(batch)
    if isinstance(batch, torch.Tensor):
        if batch.dtype == torch.float64:
            batch = batch.float()
        return batch.to(device, non_blocking=True)
    return batch


def resolve_device(requested: str) -> torch.device:
    """The torch device a ``--device`` value names: auto (CUDA if this machine has it, else the CPU), cpu, cuda or
    cuda:N. A name torch does not know, or a GPU this machine does not have, is a UserError naming the choices."""
    import torch  # heavy: only the commands that build a model get here

    if requested == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(requested)
    except (RuntimeError, ValueError, TypeError):
        raise UserError(f"--device {requested}: not a device; expected auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if not count:
            raise UserError(f"--device {requested}: this machine has no CUDA GPU that torch can use; use cpu or auto")
        if device.index is not None and device.index >= count:
            raise UserError(f"--device {requested}: this machine has {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}")
    elif device.type != "cpu":
        raise UserError(f"--device {requested}: bpp runs on cpu or cuda; expected auto, cpu, cuda or cuda:N")
    return device
