"""Full disks, interrupted commands and file names made from task ids.

A command that a full disk stops names the path it could not write and leaves nothing half-written; an evaluation is
reused only when every file it recorded is there whole. Ctrl-C and SIGTERM end ``bpp draw generate``, ``bpp train``
and ``bpp eval`` (real processes here) with one line and the status 130 or 143, their worker processes stopped and no
temporary file or half-written store, checkpoint or report left. A task id becomes a file name through one function,
one name per id, bounded in length, derived before any rollout runs.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bpp.cli import main
from bpp.evaluation import report

V = [[[0.2, 0.2], [0.5, 0.8], [0.8, 0.2]]]
"""A drawing's strokes: one V."""
QUICK = ["--rollouts", "1", "--max-steps", "8", "--workers", "1"]
"""The shortest evaluation."""
FULL = "No space left on device"


@pytest.fixture(scope="module")
def run(debug_store, tmp_path_factory) -> Path:
    """A 2-step debug run on the debug store."""
    path = tmp_path_factory.mktemp("interrupts") / "run"
    main(["train", "--data", str(debug_store.path), "--out", str(path), "--preset", "debug", "--steps", "2"])
    return path


def _refused(argv: list[str], capsys) -> str:
    """Runs ``bpp argv``, which must end with one line (no traceback); returns it."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(argv)
    message = stop.value.code
    assert isinstance(message, str) and "\n" not in message.strip(), message
    assert "Traceback" not in capsys.readouterr().err
    return message


def _leftovers(folder: Path) -> list[str]:
    """Temporary files and folders of interrupted writers under `folder`."""
    return sorted(str(p) for p in folder.rglob("*") if ".partial" in p.name or ".tmp-" in p.name or ".lock" in p.name)


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, FULL)  # as the system reports it to zarr, PIL or ffmpeg's pipe: no file named


# ----------------------------------------------------------------------------- names from task ids

IDS = ["a/b", "a_b", "star.v1", "star.v2", "x" * 300, "hershey-G", "hershey-g", "..", ".hidden", "a_b-0123456789"]
"""Ids that a lossy file name would merge (a separator, a suffix taken for the file's, the case on macOS, a name
that looks hashed), or that are too long, hidden or a path."""


def test_file_stem_gives_one_bounded_name_per_id_and_keeps_plain_ids():
    from bpp.utils import file_stem

    names = [file_stem(task_id) for task_id in IDS]
    assert len({name.casefold() for name in names}) == len(IDS)  # distinct even on a case-insensitive file system
    assert all(0 < len(name) <= 100 and "/" not in name and not name.startswith(".") for name in names)
    assert names[4].startswith("x" * 80 + "-")  # readable: a slug of the id, then a hash
    for plain in ["procedural-00001", "hershey-star", "train-000-s1-bpr-pl", "task.1"]:
        assert file_stem(plain) == plain


@pytest.mark.slow
def test_eval_writes_one_video_per_task_id(run, tmp_path):
    drawings = tmp_path / "ids.json"
    drawings.write_text(json.dumps({"drawings": [{"id": task_id, "strokes": V} for task_id in IDS]}))
    out = tmp_path / "eval"
    argv = ["eval", str(run), "--files", str(drawings), *QUICK, "--videos", str(len(IDS)), "--out", str(out)]
    main([*argv, "--data-dir", str(tmp_path / "data")])
    results = json.loads((out / "results.json").read_text())
    videos = [task["video"] for task in results["tasks"]]
    assert [task["task_id"] for task in results["tasks"]] == IDS
    assert len(set(videos)) == len(IDS) and all(name in results["outputs"] for name in videos)
    assert sorted(p.name for p in out.glob("rollout_*")) == sorted(videos)  # none overwrote another
    assert all(len(name) < 120 for name in videos)


def test_a_video_the_mp4_encoder_fails_on_is_a_gif_with_a_warning_and_a_full_disk_is_an_error(tmp_path, monkeypatch):
    written, frames = report.save_animation, [np.zeros((16, 16, 3), np.uint8)] * 3
    failure = RuntimeError("no libx264")

    def encoder(frames, path):
        if Path(path).suffix == ".mp4":
            raise failure
        return written(frames, path)

    monkeypatch.setattr(report, "save_animation", encoder)
    with pytest.warns(UserWarning, match=r"rollout_a\.mp4 failed \(RuntimeError: no libx264\); writing a GIF"):
        path = report.write_video(frames, tmp_path / "rollout_a")
    assert path.name == "rollout_a.gif" and [p.name for p in tmp_path.iterdir()] == ["rollout_a.gif"]
    failure = OSError(errno.ENOSPC, FULL)
    with pytest.raises(OSError, match=FULL):
        report.write_video(frames, tmp_path / "rollout_b")
    assert [p.name for p in tmp_path.iterdir()] == ["rollout_a.gif"]


def test_ffmpeg_is_started_by_vfork_so_a_large_process_can_write_a_video(tmp_path, monkeypatch):
    monkeypatch.delenv("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", raising=False)
    started, popen = [], subprocess.Popen

    def spy(cmd, *args, **kwargs):  # a preexec function makes Python fork, duplicating the caller's address space
        started.append((Path(cmd[0]).name, kwargs.get("preexec_fn")))
        return popen(cmd, *args, **kwargs)

    monkeypatch.setattr(subprocess, "Popen", spy)
    path = report.write_video([np.zeros((16, 16, 3), np.uint8)] * 3, tmp_path / "rollout_a")
    assert path.name == "rollout_a.mp4"
    assert len(started) >= 2 and all("ffmpeg" in name and pre is None for name, pre in started)  # writer, checker


def test_eval_refuses_an_output_folder_it_cannot_write_before_any_rollout(run, debug_store, tmp_path, monkeypatch):
    import bpp.evaluation.evaluate as evaluate

    def rollouts(*args, **kwargs):
        raise AssertionError("the rollouts ran before the output folder was checked")

    monkeypatch.setattr(evaluate, "run_protocol", rollouts)
    (tmp_path / "notes.txt").write_text("mine")
    out = tmp_path / "notes.txt" / "eval"
    with pytest.raises(SystemExit) as stop:
        main(["eval", str(run), "--tasks", str(debug_store.path), "--num-tasks", "1", *QUICK, "--out", str(out)])
    assert stop.value.code == f"bpp eval: error: --out {out}: {tmp_path / 'notes.txt'} is not a folder"
    assert (tmp_path / "notes.txt").read_text() == "mine"


# ----------------------------------------------------------------------------- full disks


def test_generation_on_a_full_disk_names_the_store_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    from zarr.storage import LocalStore

    writes = []
    put = LocalStore.set

    async def set_until_full(self, key, value):
        writes.append(key)
        if len(writes) > 3:  # the header and a few arrays are written, then the disk is full
            _no_space()
        await put(self, key, value)

    monkeypatch.setattr(LocalStore, "set", set_until_full)
    out = tmp_path / "new.zarr"
    message = _refused(["draw", "generate", "--preset", "debug", "--workers", "1", "--out", str(out)], capsys)
    assert message == f"bpp draw generate: error: {out}: {FULL}"
    assert len(writes) > 3 and not out.exists() and not list(tmp_path.iterdir())


def test_training_on_a_full_disk_names_the_checkpoint_and_leaves_no_temporary_folder(
    debug_store, tmp_path, monkeypatch, capsys
):
    from safetensors import SafetensorError

    import bpp.checkpoint as checkpoint

    def save_file(tensors, path):
        Path(path).write_bytes(b"\0" * 100)  # what fitted on the disk
        raise SafetensorError(f"Error while serializing: I/O error: {FULL} (os error 28)")

    monkeypatch.setattr(checkpoint, "save_file", save_file)
    run = tmp_path / "run"
    argv = ["train", "--data", str(debug_store.path), "--out", str(run), "--preset", "debug", "--steps", "1"]
    message = _refused(argv, capsys)
    assert message == f"bpp train: error: {run / 'checkpoints' / 'step_00000001'}: {FULL}"
    assert list((run / "checkpoints").iterdir()) == []


def test_a_checkpoint_left_half_written_by_a_killed_process_is_removed_by_the_next_save(debug_store, tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)  # a process that has ended
    checkpoints = tmp_path / "run" / "checkpoints"
    for name in (f".step_00000005.partial-{pid}-0123abcd", f".step_00000005.tmp-{pid}"):  # now and before bpp 0.1
        (checkpoints / name).mkdir(parents=True)
        (checkpoints / name / "model.safetensors").write_bytes(b"\0" * 1000)
    alive = checkpoints / f".step_00000009.partial-{os.getpid()}-0123abcd"  # a save still running: kept
    alive.mkdir()
    argv = ["train", "--data", str(debug_store.path), "--out", str(tmp_path / "run"), "--preset", "debug"]
    main([*argv, "--steps", "1"])
    assert sorted(p.name for p in checkpoints.iterdir()) == [alive.name, "last", "step_00000001"]


def _fail_on(output: str, monkeypatch) -> None:
    """Make the disk fill up while the evaluation writes `output` (its report, its picture or a video), once a part
    of it is written; the system names no file, as for zarr, PIL or ffmpeg's pipe."""
    import imageio.v2
    import imageio.v3
    import matplotlib.figure

    if output == "report":
        write_text = Path.write_text

        def write_half(self, text, *args, **kwargs):
            if self.suffix == ".md" and "results" in self.name:
                write_text(self, text[: len(text) // 2])
                _no_space()
            return write_text(self, text, *args, **kwargs)

        monkeypatch.setattr(Path, "write_text", write_half)
    elif output == "picture":
        savefig = matplotlib.figure.Figure.savefig

        def save_empty(self, path, *args, **kwargs):
            if "grid" in Path(path).name:
                Path(path).write_bytes(b"")
                _no_space()
            return savefig(self, path, *args, **kwargs)

        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", save_empty)
    else:  # ffmpeg's MP4 cut short, then the GIF it falls back to
        get_writer, imwrite = imageio.v2.get_writer, imageio.v3.imwrite

        class CutShort:
            def __init__(self, path):
                self.path = Path(path)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return False

            def append_data(self, frame):
                self.path.write_bytes(b"\0" * 48)
                _no_space()

        def writer(path, *args, **kwargs):
            return CutShort(path) if "rollout" in Path(path).name else get_writer(path, *args, **kwargs)

        def write_gif(path, *args, **kwargs):
            if "rollout" in str(path) or path == "<bytes>":
                _no_space()
            return imwrite(path, *args, **kwargs)

        monkeypatch.setattr(imageio.v2, "get_writer", writer)
        monkeypatch.setattr(imageio.v3, "imwrite", write_gif)


@pytest.mark.parametrize(("output", "file"), [("report", "results.md"), ("picture", "grid.png"), ("video", "rollout_")])
def test_an_evaluation_stopped_by_a_full_disk_is_not_reused_and_is_written_whole_again(
    output, file, run, debug_store, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "eval"
    argv = ["eval", str(run), "--tasks", str(debug_store.path), "--num-tasks", "1", *QUICK, "--out", str(out)]
    with monkeypatch.context() as patch:
        _fail_on(output, patch)
        message = _refused(argv, capsys)
    assert message.startswith(f"bpp eval: error: {out / file}") and message.endswith(f": {FULL}"), message
    assert not (out / "results.json").exists() and not _leftovers(tmp_path)
    assert not [p for p in out.iterdir() if p.stat().st_size == 0]  # no empty picture, no cut-short file
    main(argv)
    assert "reusing" not in capsys.readouterr().out
    results = json.loads((out / "results.json").read_text())
    assert {"results.md", "grid.png", "attention.png"} <= set(results["outputs"])
    for name, size in results["outputs"].items():
        assert (out / name).stat().st_size == size > 0


def test_an_evaluation_whose_video_was_cut_short_later_is_run_again(run, debug_store, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = ["eval", str(run), "--tasks", str(debug_store.path), "--num-tasks", "1", *QUICK, "--out", str(out)]
    main(argv)
    (video,) = out.glob("rollout_*")
    size = video.stat().st_size
    video.write_bytes(video.read_bytes()[:100])
    capsys.readouterr()
    main(argv)
    assert "reusing" not in capsys.readouterr().out and video.stat().st_size == size
    main(argv)
    assert "reusing" in capsys.readouterr().out


# ----------------------------------------------------------------------------- Ctrl-C and SIGTERM


def _children(pid: int) -> set[int]:
    """The processes whose parent is `pid` (Linux's /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _interrupt(argv: list[str], ready, signum: int, to_group: bool, workers: int) -> tuple[str, set[int]]:
    """Runs ``bpp argv``; once `ready()` and its `workers` worker processes run, sends it `signum` (to its whole
    process group, as a Ctrl-C in a terminal does, if `to_group`). Returns its stderr and its workers' ids."""
    command = [sys.executable, "-m", "bpp.cli", *argv]
    proc = subprocess.Popen(
        command,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        # as from a terminal: pytest-xdist's workers ignore SIGINT, and a child inherits that (a command started
        # with SIGINT ignored, like a shell's background job, rightly keeps ignoring it)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 240
    workers_seen: set[int] = set()
    while proc.poll() is None and time.monotonic() < deadline:
        workers_seen = _children(proc.pid)
        if len(workers_seen) >= workers and ready():
            break
        time.sleep(0.05)
    assert proc.poll() is None, f"it ended before the moment to interrupt it: {proc.stderr.read()[-2000:]}"
    if to_group:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err[-3000:]
    return err, workers_seen


def _check_interrupted(err: str, command: str, signum: int, workers: set[int]) -> None:
    assert "Traceback" not in err, err[-3000:]
    assert err.rstrip().splitlines()[-1] == f"bpp {command}: interrupted by {signal.Signals(signum).name}", err[-500:]
    deadline = time.monotonic() + 10  # ended workers are reaped by the system a moment after their parent ends
    while any(map(_running, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(map(_running, workers))


CTRL_C = pytest.param(signal.SIGINT, True, id="ctrl-c")  # a terminal's Ctrl-C reaches every process of the command
SIGTERM = pytest.param(signal.SIGTERM, False, id="sigterm")  # `kill PID`: the command's process alone
SIGTERM_TO_ALL = pytest.param(signal.SIGTERM, True, id="sigterm-to-all")  # a job scheduler, systemd: all of them
needs_proc = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds worker processes in /proc")


@pytest.mark.slow
@needs_proc
@pytest.mark.parametrize(("signum", "to_group"), [CTRL_C, SIGTERM_TO_ALL])
def test_an_interrupted_generation_ends_in_one_line_and_leaves_no_store(signum, to_group, tmp_path):
    out = tmp_path / "new.zarr"
    argv = ["draw", "generate", "--preset", "debug", "--num-tasks", "5000", "--workers", "2", "--out", str(out)]
    err, workers = _interrupt(argv, lambda: any(tmp_path.glob(".new.zarr.partial-*")), signum, to_group, 2)
    _check_interrupted(err, "draw generate", signum, workers)
    assert not out.exists() and not list(tmp_path.iterdir())  # no store, no partial folder, no lock


@pytest.mark.slow
@needs_proc
@pytest.mark.parametrize(("signum", "to_group"), [CTRL_C, SIGTERM_TO_ALL])
def test_an_interrupted_training_ends_in_one_line_with_whole_checkpoints(signum, to_group, debug_store, tmp_path):
    run = tmp_path / "run"
    argv = ["train", "--data", str(debug_store.path), "--out", str(run), "--preset", "debug", "--steps", "2000"]
    argv += ["--save-every", "1", "--workers", "2"]  # a checkpoint every step: the signal comes while one is saved
    err, workers = _interrupt(argv, lambda: (run / "checkpoints" / "last").exists(), signum, to_group, 2)
    _check_interrupted(err, "train", signum, workers)
    assert not _leftovers(tmp_path)
    checkpoints = run / "checkpoints"
    assert (checkpoints / (checkpoints / "last").read_text()).is_dir()
    for step in checkpoints.glob("step_*"):
        names = {"model.safetensors", "ema.safetensors", "optimizer.safetensors", "rng.safetensors", "state.json"}
        assert {p.name for p in step.iterdir()} == names


@pytest.mark.slow
@needs_proc
@pytest.mark.parametrize(("signum", "to_group"), [CTRL_C, SIGTERM, SIGTERM_TO_ALL])
def test_an_interrupted_evaluation_ends_in_one_line_and_writes_nothing(signum, to_group, run, debug_store, tmp_path):
    out = tmp_path / "eval"
    argv = ["eval", str(run), "--tasks", str(debug_store.path), "--rollouts", "4", "--max-steps", "300"]
    err, workers = _interrupt([*argv, "--workers", "2", "--out", str(out)], lambda: True, signum, to_group, 2)
    _check_interrupted(err, "eval", signum, workers)
    assert not out.exists()


def _catches(pid: int, signum: int) -> bool:
    """Whether process `pid` has a handler for `signum` (Linux's /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    return False


@needs_proc
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_command_interrupted_while_it_loads_ends_in_one_line(signum):
    """The command line takes seconds to import torch and the benchmarks: a signal then ends it as it would later."""
    from importlib.metadata import entry_points

    (program,) = entry_points(group="console_scripts", name="bpp")
    assert program.value == "bpp.launch:main"  # the `bpp` program too
    proc = subprocess.Popen(
        [sys.executable, "-m", "bpp", "train", "--help"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 30
    while not _catches(proc.pid, signal.SIGTERM) and time.monotonic() < deadline:  # the entry point's handlers are in
        time.sleep(0.002)
    loading = "libtorch" not in Path(f"/proc/{proc.pid}/maps").read_text()
    proc.send_signal(signum)
    assert loading, "the command line took signals only once torch was loaded"
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum and "Traceback" not in err, err[-3000:]
    assert re.fullmatch(rf"bpp( train)?: interrupted by {signal.Signals(signum).name}", err.strip()), err[-500:]


_SIGNAL_INSIDE_A_FINALIZER = """
import os, signal, sys, time
from bpp.errors import Interrupted, raise_interrupted
signal.signal(signal.SIGTERM, raise_interrupted)
class Finalized:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100_000):  # the handler raises here, where Python can only ignore the exception
            pass
try:
    Finalized()
    time.sleep(20)
    print("went on")
except Interrupted as err:
    print("stopped by", err.signum)
"""


@needs_proc
def test_a_signal_raised_where_python_ignores_exceptions_still_stops_the_command():
    """A signal that comes while a finalizer or an import lock's callback runs cannot stop the program there: it stops
    it at the next ordinary line, without a traceback, instead of being lost."""
    start = time.monotonic()
    script = [sys.executable, "-c", _SIGNAL_INSIDE_A_FINALIZER]
    done = subprocess.run(script, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == f"stopped by {int(signal.SIGTERM)}", done
    assert "Traceback" not in done.stderr and time.monotonic() - start < 15, done
