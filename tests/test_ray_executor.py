"""Generation and evaluation on a real Ray cluster (a head and worker nodes as separate processes on 127.0.0.1, one CPU
each) give the local executor's store and results, bit for bit, even when a node is killed mid-run."""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from bpp.cli import main
from bpp.data.store import EpisodeStore
from helpers import import_optional

pytestmark = [pytest.mark.ray, pytest.mark.slow]
ray = import_optional("ray", "ray")
psutil = import_optional("psutil", "ray")


class Cluster:
    """A Ray cluster of separate processes on this machine: ``ray start --block`` for the head and each worker node."""

    def __init__(self, folder: Path):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.address = f"127.0.0.1:{self.port}"
        self.folder = folder
        self.temp = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # Ray's socket paths must stay short
        self.nodes: list[subprocess.Popen] = []
        # The cluster's token, which its drivers need too; a dead node is noticed within seconds instead of Ray's
        # default half a minute.
        auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": os.urandom(16).hex()}
        self.env = {**os.environ, **auth, "RAY_USAGE_STATS_ENABLED": "0", "RAY_health_check_period_ms": "500",
                    "RAY_health_check_timeout_ms": "1000", "RAY_health_check_failure_threshold": "3",
                    "OMP_NUM_THREADS": "1", "TMPDIR": str(self.temp)}  # fmt: skip

    def start(self) -> None:
        """The head node, then one worker node."""
        self._start("--head", f"--port={self.port}", "--include-dashboard=false", "--disable-usage-stats",
                    f"--temp-dir={self.temp}")  # fmt: skip
        self.add_node()

    def _start(self, *flags: str) -> subprocess.Popen:
        ray_cli = Path(sys.executable).with_name("ray")
        log = open(self.folder / f"node-{len(self.nodes)}.log", "w")  # noqa: SIM115 - the node's lifetime
        node = subprocess.Popen([ray_cli, "start", "--block", "--node-ip-address=127.0.0.1", "--num-cpus=1", *flags],
                                stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)  # fmt: skip
        self.nodes.append(node)
        self.wait_for(len(self.nodes))
        return node

    def add_node(self) -> subprocess.Popen:
        return self._start(f"--address={self.address}")

    def alive(self) -> int:
        """Nodes the cluster counts as alive."""
        script = f"import ray; ray.init(address={self.address!r}); print(sum(n['Alive'] for n in ray.nodes()))"
        found = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=self.env)
        return int(found.stdout.split()[-1]) if found.returncode == 0 and found.stdout.split() else 0

    def wait_for(self, nodes: int, timeout: float = 90) -> None:
        deadline = time.time() + timeout
        while self.alive() != nodes:
            assert time.time() < deadline, (self.folder / f"node-{len(self.nodes) - 1}.log").read_text()[-3000:]
            time.sleep(0.5)

    def bpp(self, *argv: str) -> subprocess.Popen:
        """The ``bpp`` command, started with `argv` and ``--executor ray`` as a driver of this cluster."""
        argv = [sys.executable, "-m", "bpp", *argv, "--executor", "ray", "--ray-address", self.address]
        return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=self.env)

    def run(self, *argv: str) -> str:
        """Run :meth:`bpp` to its end; its output."""
        process = self.bpp(*argv)
        out, _ = process.communicate(timeout=600)
        assert process.returncode == 0, out[-3000:]
        return out

    @staticmethod
    def kill(node: subprocess.Popen) -> None:
        """SIGKILL a node and every process it started (its raylet, its workers): a machine that dies."""
        processes = [psutil.Process(node.pid), *psutil.Process(node.pid).children(recursive=True)]
        for process in processes:
            with contextlib.suppress(psutil.NoSuchProcess):
                process.kill()
        node.wait()

    def stop(self) -> None:
        for node in reversed(self.nodes):
            self.kill(node)
        subprocess.run(["rm", "-rf", str(self.temp)], check=False)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    cluster = Cluster(tmp_path_factory.mktemp("ray"))
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


def test_a_drawing_store_generated_on_the_cluster_is_the_local_store(cluster, tmp_path):
    main(["draw", "generate", "--preset", "debug", "--out", str(tmp_path / "local.zarr"), "--workers", "1"])
    out = cluster.run("draw", "generate", "--preset", "debug", "--out", str(tmp_path / "ray.zarr"))
    local, on_ray = EpisodeStore(tmp_path / "local.zarr"), EpisodeStore(tmp_path / "ray.zarr")
    assert on_ray.fingerprint() == local.fingerprint()
    assert re.search(r"\[ray\] 12 jobs on [12] nodes:\n  node \w+ \(.*\): \d+ jobs", out), out[-2000:]


def test_a_node_killed_mid_run_costs_only_its_unfinished_tasks(cluster, tmp_path):
    argv = ["draw", "generate", "--preset", "debug", "--num-tasks", "40", "--demos-per-task", "20"]
    main([*argv, "--out", str(tmp_path / "local.zarr"), "--workers", "1"])
    doomed = cluster.add_node()
    driver = cluster.bpp(*argv, "--out", str(tmp_path / "ray.zarr"))
    deadline = time.time() + 300
    while not _running_a_job(doomed):
        assert driver.poll() is None, "the generation ended before a node could be killed: give it more tasks"
        assert time.time() < deadline
        time.sleep(0.01)
    cluster.kill(doomed)  # while it runs a job
    cluster.nodes.remove(doomed)
    out, _ = driver.communicate(timeout=600)
    assert driver.returncode == 0, out[-3000:]
    local, on_ray = EpisodeStore(tmp_path / "local.zarr"), EpisodeStore(tmp_path / "ray.zarr")
    assert on_ray.fingerprint() == local.fingerprint()
    cluster.wait_for(2)


def _running_a_job(node: subprocess.Popen) -> bool:
    """Whether a worker process of `node` runs a job (Ray names a worker's process after the task it runs)."""
    with contextlib.suppress(psutil.Error):
        return any("_run_on_node" in " ".join(p.cmdline()) for p in psutil.Process(node.pid).children(recursive=True))
    return False


@pytest.mark.libero
def test_a_libero_gen_store_generated_on_the_cluster_is_the_local_store(cluster, tmp_path):
    argv = ["libero", "generate", "--preset", "debug", "--task-indices", "0", "--demos-per-task", "1"]
    main([*argv, "--out", str(tmp_path / "local.zarr"), "--workers", "1"])
    cluster.run(*argv, "--out", str(tmp_path / "ray.zarr"))
    local, on_ray = EpisodeStore(tmp_path / "local.zarr"), EpisodeStore(tmp_path / "ray.zarr")
    assert on_ray.fingerprint() == local.fingerprint()


def test_an_evaluation_on_the_cluster_gives_the_local_results(cluster, debug_store, tmp_path):
    run = tmp_path / "run"
    main(["train", "--method", "bpp", "--data", str(debug_store.path), "--out", str(run), "--preset", "debug",
          "--steps=2"])  # fmt: skip
    flags = ["--tasks", "train", "--num-tasks", "4", "--rollouts", "2", "--max-steps", "30", "--videos", "1"]
    # Two local workers have a torch thread each, as a Ray task does: the thread count changes the floating-point sums.
    main(["eval", str(run), *flags, "--workers", "2", "--out", str(tmp_path / "local")])
    cluster.run("eval", str(run), *flags, "--out", str(tmp_path / "ray"))
    local, on_ray = (json.loads((tmp_path / name / "results.json").read_text()) for name in ("local", "ray"))
    for key in ("summary", "tasks", "rollouts"):
        assert on_ray[key] == local[key], key
    assert (tmp_path / "ray" / "grid.png").read_bytes() == (tmp_path / "local" / "grid.png").read_bytes()


def test_executor_flags_are_checked_before_anything_runs(tmp_path, capsys):
    out = str(tmp_path / "x.zarr")
    for flags, message in [
        (["--executor", "ray", "--workers", "2"], "--workers is for --executor local"),
        (["--ray-address", "127.0.0.1:1"], "--ray-address needs --executor ray"),
        (["--executor", "ray", "--ray-address", "127.0.0.1:1"], "127.0.0.1:1: cannot reach a Ray cluster there"),
    ]:
        with pytest.raises(SystemExit) as exited:
            main(["draw", "generate", "--out", out, *flags])
        said = f"{exited.value.code} {capsys.readouterr().err}"  # the parser's report, or main's one-line error
        assert message in " ".join(said.split()), flags
    assert not list(tmp_path.iterdir())


def test_a_ray_address_from_the_environment_that_nothing_answers_is_refused_at_once(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    started = time.monotonic()
    with pytest.raises(SystemExit) as exited:
        main(["draw", "generate", "--preset", "debug", "--out", str(tmp_path / "x.zarr"), "--executor", "ray"])
    said = " ".join(f"{exited.value.code} {capsys.readouterr().err}".split())
    assert "RAY_ADDRESS=127.0.0.1:1" in said and "cannot reach a Ray cluster there" in said
    assert time.monotonic() - started < 30
    assert not list(tmp_path.iterdir())


def test_the_local_executor_never_imports_ray(tmp_path):
    script = (
        "import sys\nfrom bpp.cli import main\n"
        f"main(['draw', 'generate', '--preset', 'debug', '--num-tasks', '2', '--out', {str(tmp_path / 's.zarr')!r}])\n"
        "assert 'ray' not in sys.modules, 'ray was imported'\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_a_shared_folder_is_unpacked_once_per_machine_and_removed_when_long_unused(tmp_path, monkeypatch):
    """What evaluation ships to nodes: unpacked whole on first use, reused, and unpacked ones nobody used for a day
    removed when another is unpacked (a node's temporary folder does not fill up); one in use stays."""
    from bpp.executor import SHARED_KEEP_S, SharedFolder

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "node-tmp"))
    (tmp_path / "node-tmp").mkdir()
    source = tmp_path / "tasks.zarr"
    (source / "data").mkdir(parents=True)
    (source / "data" / "chunk").write_bytes(b"\x00\x01" * 1000)
    first = SharedFolder.pack(source)
    path = Path(first.unpack())
    assert path.name == "tasks.zarr" and (path / "data" / "chunk").read_bytes() == b"\x00\x01" * 1000
    (path / "data" / "chunk").write_bytes(b"changed")  # a second job finds it unpacked: not unpacked again
    assert Path(first.unpack()) == path and (path / "data" / "chunk").read_bytes() == b"changed"
    long_ago = time.time() - SHARED_KEEP_S - 60
    os.utime(path.parent, (long_ago, long_ago))
    (source / "data" / "chunk").write_bytes(b"another store")
    second = SharedFolder.pack(source)
    assert second.digest != first.digest
    in_use = Path(second.unpack())
    assert not path.parent.exists()  # unused for more than a day: removed
    os.utime(in_use.parent, (long_ago, long_ago))
    assert Path(second.unpack()) == in_use  # used again: marked
    SharedFolder.pack(source / "data").unpack()
    assert in_use.exists()
