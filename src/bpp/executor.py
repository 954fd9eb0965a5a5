"""Where generation and evaluation run their jobs: processes on this machine (the default), or a Ray cluster.

A job is a pure function of its arguments (a task's seeds, a rollout's seed): the same jobs give the same results
wherever they run and in whatever order they finish. So a caller hands an executor a function and its jobs, consumes
the results as they come (one progress bar however many machines work), and writes its store or results itself,
once, in its own order: the same bytes from either executor.

* :class:`Local`: a pool of processes on this machine (:func:`bpp.utils.worker_pool`), or the caller's own process
  for one worker. Imports nothing beyond the standard library.
* :class:`Ray`: tasks on a Ray cluster the user runs (``ray start --head``, ``ray start --address ...``), one CPU
  each. A worker process or a node that dies costs only its unfinished jobs, which Ray runs again (``retries``).
  Every node needs the same bpp installed; nothing else is shared: jobs, results and the folders a job reads
  (:meth:`Executor.share`) travel through Ray's object store.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import multiprocessing as mp
import os
import re
import shutil
import socket
import tarfile
import tempfile
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from bpp.errors import UserError
from bpp.utils import usable_cores, worker_pool

__all__ = ["Executor", "Local", "Ray", "SharedFolder", "as_executor", "check_executor_flags", "make_executor"]


class Executor:
    """Runs ``fn(job)`` for every job and yields the results (see the module's docstring)."""

    def map(
        self,
        fn: Callable[[Any], Any],
        jobs: Iterable[Any],
        *,
        ordered: bool = False,
        initializer: Callable[..., None] | None = None,
        initargs: tuple = (),
        start_method: str = "spawn",
        chunksize: int = 1,
    ) -> Iterator[Any]:
        """``fn(job)`` for every job, in the jobs' order with `ordered`, else as they finish. ``initializer(*initargs)``
        runs once in each worker process before its first job (e.g. to load a policy). `start_method` (``fork`` or
        ``spawn``) and `chunksize` (up to that many jobs sent to a worker together, fewer when there are too few jobs
        to keep every worker busy) concern local processes only. `fn` and `initializer` must be
        importable module-level functions; the jobs and results must pickle."""
        raise NotImplementedError

    def threads(self, jobs: int) -> int:
        """Torch threads for each worker process: ``OMP_NUM_THREADS`` if set (e.g. to leave cores to a training run:
        more threads than free cores slows torch down many times over), else the cores a worker has to itself."""
        return int(os.environ.get("OMP_NUM_THREADS") or 0) or self._cores_per_worker(jobs)

    def _cores_per_worker(self, jobs: int) -> int:
        raise NotImplementedError

    def share(self, folder: str | Path) -> str | SharedFolder:
        """`folder` as a job argument: its path for local processes; its contents for a cluster, whose nodes may not
        see this machine's disk (a job calls :func:`local_path` on it)."""
        return str(folder)


def local_path(folder: str | SharedFolder) -> str:
    """In a job: the local path of a folder passed through :meth:`Executor.share`."""
    return folder if isinstance(folder, str) else folder.unpack()


@dataclass(frozen=True)
class Local(Executor):
    """Processes on this machine: `processes` of them (0: one per core); one runs the jobs in the caller's process."""

    processes: int = 0

    def workers(self, jobs: int) -> int:
        """How many processes run `jobs` jobs."""
        return max(1, min(self.processes or usable_cores(), jobs))

    def _cores_per_worker(self, jobs: int) -> int:
        return max(1, usable_cores() // self.workers(jobs))

    def map(self, fn, jobs, *, ordered=False, initializer=None, initargs=(), start_method="spawn", chunksize=1):
        jobs = list(jobs)
        workers = self.workers(len(jobs))
        if workers == 1:
            if initializer is not None:
                initializer(*initargs)
            yield from map(fn, jobs)
            return
        if start_method not in mp.get_all_start_methods():
            start_method = "spawn"
        # The pool is stopped however the caller stops reading (an error, Ctrl-C, SIGTERM): see worker_pool.
        with worker_pool(mp.get_context(start_method), workers, initializer, initargs) as pool:
            chunksize = max(1, min(chunksize, len(jobs) // (8 * workers)))
            yield from (pool.imap if ordered else pool.imap_unordered)(fn, jobs, chunksize)


@dataclass
class Ray(Executor):
    """Jobs as tasks of a Ray cluster, one CPU each.

    `address`: the cluster's (``host:port`` of its head, or ``auto``); empty: ``RAY_ADDRESS`` if set, else a
    cluster already running on this machine, else a new one on this machine for the duration of each call.
    `retries`: how many times a job whose worker process or node died is run again."""

    address: str = ""
    retries: int = 3
    progress: bool = True
    done: list[tuple[str, float]] = field(default_factory=list, init=False, repr=False)
    """The last call's finished jobs, in the order they finished: (the node that ran it, seconds it took)."""

    def _cores_per_worker(self, jobs: int) -> int:
        return 1  # a job holds one of the cluster's CPUs

    def share(self, folder: str | Path) -> SharedFolder:
        return SharedFolder.pack(folder)

    @contextlib.contextmanager
    def _connected(self):
        ray = _import_ray()
        if ray.is_initialized():
            yield ray
            return
        _check_reachable(self.address)
        try:
            ray.init(address=self.address or None, log_to_driver=False, configure_logging=False)
        except (ConnectionError, RuntimeError, ValueError) as err:
            raise UserError(f"--ray-address {self.address or '(default)'}: cannot reach a Ray cluster: {err}") from None
        try:
            yield ray
        finally:
            ray.shutdown()

    def map(self, fn, jobs, *, ordered=False, initializer=None, initargs=(), start_method="spawn", chunksize=1):
        jobs = list(jobs)
        with self._connected() as ray:
            run = ray.remote(_run_on_node).options(num_cpus=1, max_retries=self.retries, retry_exceptions=False)
            setup = ray.put((uuid.uuid4().hex, initializer, initargs)) if initializer is not None else None
            pending = {run.remote(fn, job, setup): i for i, job in enumerate(jobs)}
            waiting: dict[int, Any] = {}  # ordered: results that finished before an earlier job's
            next_index = 0
            self.done.clear()
            try:
                while pending:
                    # All that finished within a moment: one scan of the pending jobs per batch, not per job.
                    ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.2)
                    for ref in ready:
                        index = pending.pop(ref)
                        result, node, seconds = _result(ray, ref)
                        self.done.append((node, seconds))
                        if not ordered:
                            yield result
                            continue
                        waiting[index] = result
                        while next_index in waiting:
                            yield waiting.pop(next_index)
                            next_index += 1
            finally:
                for ref in pending:  # an error or an interrupt: the cluster's CPUs go back to their owners
                    with contextlib.suppress(Exception):
                        ray.cancel(ref, force=True)
            if self.progress and self.done:
                tqdm.write(self.summary())

    def summary(self) -> str:
        """The last call's jobs per node, and their seconds of work."""
        jobs, seconds = Counter(), Counter()
        for node, took in self.done:
            jobs[node] += 1
            seconds[node] += took
        lines = [f"  {node}: {jobs[node]} jobs, {seconds[node]:.1f} s of work" for node in sorted(jobs)]
        return "\n".join([f"[ray] {len(self.done)} jobs on {len(jobs)} nodes:", *lines])


def _check_reachable(address: str, timeout: float = 10.0) -> None:
    """Refuse a ``host:port`` address nothing answers at, in seconds (Ray itself retries for minutes). An empty
    `address` is ``RAY_ADDRESS``'s, if set, which Ray would use: it is checked the same way and named as such."""
    named = f"--ray-address {address}"
    if not address and os.environ.get("RAY_ADDRESS", "").strip():
        address = os.environ["RAY_ADDRESS"].strip()
        named = f"RAY_ADDRESS={address} (the environment's, as no --ray-address was given)"
    host, _, port = address.rpartition(":")
    if not host or not re.fullmatch("[0-9]+", port) or "://" in address:
        return  # "", "auto" or a ray:// client address: left to Ray
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as err:
        raise UserError(f"{named}: cannot reach a Ray cluster there ({err})") from None


RAY_MISSING = "--executor ray needs Ray: pip install -e '.[ray]' in bpp's clone"


def _import_ray():
    try:
        # Ray: the ray extra
        import ray
    except ImportError:
        raise UserError(RAY_MISSING) from None
    return ray


def _result(ray, ref) -> tuple[Any, str, float]:
    """A finished job's (result, node, seconds); a job's own error is raised as itself, not wrapped in Ray's."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        cause = getattr(err, "cause", None)
        if isinstance(cause, BaseException):
            raise cause from None
        raise


_SETUP: dict[str, Any] = {}


def _run_on_node(fn, job, setup) -> tuple[Any, str, float]:
    """A Ray task: `setup`'s initializer once per worker process and call, then ``fn(job)``; returns the result, the
    node that ran it and the seconds it took."""
    if setup is not None and _SETUP.get("key") != setup[0]:
        key, initializer, initargs = setup
        initializer(*initargs)
        _SETUP["key"] = key
    t0 = time.perf_counter()
    result = fn(job)
    # Ray: the ray extra
    import ray

    node = f"node {ray.get_runtime_context().get_node_id()[:8]} ({socket.gethostname()})"
    return result, node, time.perf_counter() - t0


@dataclass(frozen=True)
class SharedFolder:
    """A folder's contents travelling with a job (a tar archive), unpacked once per machine where a job needs it."""

    name: str
    digest: str
    archive: bytes

    @classmethod
    def pack(cls, folder: str | Path) -> SharedFolder:
        folder = Path(folder)
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as tar:
            tar.add(folder, arcname=folder.name)
        data = buffer.getvalue()
        return cls(folder.name, hashlib.sha256(data).hexdigest()[:16], data)

    def unpack(self) -> str:
        """The folder's path on this machine: ``<tmp>/bpp-shared/<digest>/<name>``, unpacked by the first job that
        needs it (into a temporary sibling, then renamed: a job running beside it never sees half a folder). Every
        job marks it used; unpacking a new one removes those no job has used for :data:`SHARED_KEEP_S` seconds, so
        a machine's temporary folder does not fill up with the stores of evaluations long finished."""
        root = Path(tempfile.gettempdir()) / "bpp-shared" / self.digest
        path = root / self.name
        if path.exists():
            with contextlib.suppress(OSError):
                os.utime(root)
        else:
            _remove_unused_shared(root.parent)
            root.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(dir=root))
            with tarfile.open(fileobj=io.BytesIO(self.archive)) as tar:
                tar.extractall(tmp, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
            try:
                os.rename(tmp / self.name, path)
            except OSError:  # another job unpacked it first
                if not path.exists():
                    raise
            shutil.rmtree(tmp, ignore_errors=True)
        return str(path)


SHARED_KEEP_S = 24 * 3600
"""How long a shared folder nobody uses stays unpacked on a machine."""


def _remove_unused_shared(folder: Path) -> None:
    with contextlib.suppress(OSError):
        for entry in folder.iterdir():
            with contextlib.suppress(OSError):
                if time.time() - entry.stat().st_mtime > SHARED_KEEP_S:
                    shutil.rmtree(entry, ignore_errors=True)


def as_executor(workers: int | Executor) -> Executor:
    """An executor from a `workers` argument: an Executor as is, a number of local processes (0: one per core)."""
    return workers if isinstance(workers, Executor) else Local(int(workers))


def check_executor_flags(kind: str, workers: int = 0, ray_address: str = "") -> None:
    """Check the command-line flags ``--executor``, ``--workers`` and ``--ray-address`` together, as parsing them
    does: without importing Ray or contacting a cluster (:func:`make_executor` does both, when the command runs)."""
    if kind == "local":
        if ray_address:
            raise UserError("--ray-address needs --executor ray")
    elif kind == "ray":
        if workers:
            raise UserError("--workers is for --executor local; a Ray cluster runs a job per CPU it has")
        if importlib.util.find_spec("ray") is None:
            raise UserError(RAY_MISSING)
    else:
        raise UserError(f"--executor {kind!r}: expected local or ray")


def make_executor(kind: str, workers: int = 0, ray_address: str = "") -> Executor:
    """The executor of the command-line flags ``--executor``, ``--workers`` and ``--ray-address``; a Ray cluster's
    address is checked to answer (a UserError otherwise)."""
    check_executor_flags(kind, workers, ray_address)
    if kind == "local":
        return Local(workers)
    _import_ray()
    _check_reachable(ray_address)
    return Ray(ray_address)
