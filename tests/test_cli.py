import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from bpp import cli
from bpp.cli import StoreInfo, main
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.runs import RUNS
from bpp.train import cpu_plan
from bpp.train_config import TrainConfig
from bpp.utils import usable_cores


def _bpp(*args, cwd=None):
    """`bpp` in its own process: what a user's shell runs (each costs seconds of imports)."""
    return subprocess.run(
        [sys.executable, "-m", "bpp.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def _refused(*args) -> str:
    """Run `bpp` in this process, expecting a refusal: the message it exits with (main's user-error path)."""
    with pytest.raises(SystemExit) as exited:
        main(list(args))
    assert exited.value.code not in (0, None)
    return str(exited.value.code)


def test_help_lists_commands():
    out = _bpp("--help")
    assert out.returncode == 0 and "bpp draw generate" in out.stdout
    assert _refused("frobnicate") == "2"


@pytest.mark.parametrize("group", ["iphumi", "lerobot", "libero", "draw", "store"])
def test_a_group_alone_lists_its_commands(group, capsys):
    """`bpp iphumi` (or `bpp iphumi --help`) lists the group's commands and succeeds; an unknown command of the group
    is refused with the same list."""
    for argv in ([group], [group, "--help"]):
        main(argv)
        out = capsys.readouterr().out
        listed = [line.split()[1] for line in out.splitlines() if line.startswith("  bpp ")]
        assert out.startswith(f"usage: bpp {group} <command>") and listed and set(listed) == {group}, out
    assert _refused(group, "frobnicate") == "2"
    assert f"bpp {group} " in capsys.readouterr().err


def test_a_group_alone_succeeds_in_a_process():
    out = _bpp("iphumi")
    assert out.returncode == 0, out.stderr
    assert "bpp iphumi process" in out.stdout and "bpp draw" not in out.stdout


@pytest.mark.slow
def test_generate_sheet_video_info(tmp_path, capsys):
    store = tmp_path / "d.zarr"
    out = _bpp("draw", "generate", "--preset", "debug", "--num-tasks", "4", "--out", str(store), "--workers", "2")
    assert out.returncode == 0, out.stderr
    assert EpisodeStore(store).num_tasks == 4
    assert "already exists" in _refused("draw", "generate", "--preset", "debug", "--out", str(store))
    main(["draw", "sheet", str(store), "--out", str(tmp_path / "s.png"), "--tasks", "2"])
    assert (tmp_path / "s.png").stat().st_size > 10_000
    main(["draw", "video", str(store), "--episode", "1", "--out", str(tmp_path / "v.gif")])
    assert (tmp_path / "v.gif").stat().st_size > 10_000
    main(["draw", "video", str(store), "--out", str(tmp_path / "v.mp4")])
    assert (tmp_path / "v.mp4").stat().st_size > 2_000
    capsys.readouterr()
    main(["store", "info", str(store)])
    assert "episodes=12" in capsys.readouterr().out


def test_user_errors_are_reported_without_traceback(tmp_path):
    out = _bpp(
        "draw",
        "generate",
        "--source",
        "files",
        "--drawings",
        str(tmp_path / "missing.json"),
        "--out",
        str(tmp_path / "x.zarr"),
    )
    assert out.returncode != 0
    assert "missing.json: no such file" in out.stderr and "Traceback" not in out.stderr
    assert "unknown preset" in _refused("draw", "generate", "--preset", "nope", "--out", str(tmp_path / "x.zarr"))
    assert "not an episode store" in _refused("store", "info", str(tmp_path))


def _store_info_raising(monkeypatch, error: BaseException) -> None:
    """Make `bpp store info` raise `error` from inside its command function."""

    def run(args):
        raise error

    monkeypatch.setitem(cli.COMMANDS, ("store", "info"), (StoreInfo, run))


@pytest.mark.parametrize(
    "error, message",
    [
        (UserError("flag --x must be >= 0, got -1"), "flag --x must be >= 0, got -1"),
        (FileNotFoundError("runs/typo: no such checkpoint"), "runs/typo: no such checkpoint"),
        (PermissionError(13, "Permission denied", "out/results.json"), "out/results.json: Permission denied"),
        (OSError(28, "No space left on device"), "No space left on device"),
    ],
)
def test_user_and_file_system_errors_end_with_one_line_naming_the_command(monkeypatch, tmp_path, error, message):
    _store_info_raising(monkeypatch, error)
    with pytest.raises(SystemExit) as exited:
        main(["store", "info", str(tmp_path)])
    assert exited.value.code == f"bpp store info: error: {message}"  # a string: printed to stderr, exit status 1


@pytest.mark.parametrize(
    "error",
    [KeyError("task"), IndexError("list index out of range"), ValueError("bad"), RuntimeError("x"), TypeError("y")],
)
def test_internal_errors_keep_their_traceback(monkeypatch, tmp_path, error):
    """A bug (any exception but a UserError or an OSError) is not dressed up as a user's mistake: it propagates."""
    _store_info_raising(monkeypatch, error)
    with pytest.raises(type(error)) as raised:
        main(["store", "info", str(tmp_path)])
    assert raised.value is error


def test_an_internal_error_in_a_process_prints_its_traceback(tmp_path):
    script = textwrap.dedent(
        """
        from bpp import cli

        def run(args):
            return {}["no such key"]

        cli.COMMANDS[("store", "info")] = (cli.StoreInfo, run)
        cli.main(["store", "info", "."])
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 1
    assert "Traceback" in out.stderr and "KeyError: 'no such key'" in out.stderr
    assert "bpp store info: error" not in out.stderr


def test_a_user_error_in_a_process_is_one_line_without_traceback(tmp_path):
    out = _bpp("eval", str(tmp_path / "typo"), "--out", str(tmp_path / "eval"))
    assert out.returncode == 1 and not (tmp_path / "eval").exists()
    assert out.stderr.strip().splitlines() == [
        f"bpp eval: error: {tmp_path / 'typo'}: no such checkpoint or run directory"
    ]
    ckpt = tmp_path / "run" / "checkpoints" / "step_00000001"
    ckpt.mkdir(parents=True)
    (ckpt / "state.json").write_text('{"format": "bpp-checkpoint", "version": 1, "step": 1}')
    (ckpt.parent / "last").write_text(ckpt.name)
    out = _bpp("eval", str(tmp_path / "run"), "--out", str(tmp_path / "eval"))
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [
        f"bpp eval: error: {ckpt / 'state.json'}: damaged checkpoint state (no optimizer, method, model_config, "
        "train_config, stats, dataset)"
    ]


def test_bad_flag_values_are_reported_by_the_parser_naming_the_field(capsys):
    with pytest.raises(SystemExit) as exited:
        main(["eval", "runs/x", "--num-tasks", "-1"])
    assert exited.value.code not in (0, None)
    assert "num_tasks must be >= 0 (0: all), got -1" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_main_job_runs_and_reuses(tmp_path):
    """The first run imports only what the core install brings (``make demo`` installs no extra): tests/core_only.py
    refuses every module an extra's distributions provide."""
    args = (
        "demo",
        *("--out-dir", str(tmp_path / "out"), "--data-dir", str(tmp_path / "data")),
        *("--run-dir", str(tmp_path / "run"), "--preset", "debug", "--num-tasks", "6", "--steps", "3"),
        *("--eval-tasks", "2", "--rollouts", "2", "--max-steps", "30", "--workers", "1"),
    )
    core_only = Path(__file__).with_name("core_only.py")
    first = subprocess.run([sys.executable, str(core_only), *args], capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "[core-only] not found: transformers" in first.stderr  # diffusers looks for it: the hiding works
    report = (tmp_path / "out" / "report.md").read_text()
    assert "| Chamfer distance, mean over tasks | **" in report and "rollout_" in report and "paper | BPP" in report
    assert " px px" not in report and "| rollouts under 5 px |" in report
    assert "its decoder sampling from noise x 0 (1: as trained)" in report  # the main job's choice, said
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["model_config"]["diffusion"]["noise_scale"] == 0.0  # and kept with the policy
    for name in ("grid.png", "attention.png", "results.json", "results.md"):
        assert (tmp_path / "out" / "eval-human" / name).stat().st_size > 300
    assert list((tmp_path / "out" / "eval-human").glob("rollout_*"))
    second = _bpp(*args)
    assert second.returncode == 0, second.stderr[-3000:]
    assert second.stdout.count("reusing") == 3  # training data, trained policy, evaluation
    assert "the evaluation set: " in second.stdout
    # The decoder's noise is how the policy acts, not what it learned: the policy is reused, the evaluation is not.
    sampled = _bpp(*args, "--noise-scale", "1")
    assert sampled.returncode == 0 and sampled.stdout.count("reusing") == 2, sampled.stderr[-3000:]
    assert "sampling from noise x 1 " in (tmp_path / "out" / "report.md").read_text()
    # The same run folder asked for another observation preset: refused, not evaluated as if it were that model.
    other = _bpp(*args, "--obs", "canvas")
    assert other.returncode != 0 and "holds a policy trained with another model" in other.stderr
    assert "Traceback" not in other.stderr
    # A longer budget than the run in the folder (an earlier main job's): said so, with the way to reuse it.
    longer = _bpp(*args, "--steps", "5")
    assert longer.returncode != 0 and "holds a run of other length (train_config.steps: 3 in the run" in longer.stderr
    assert "Traceback" not in longer.stderr


@pytest.mark.slow
def test_eval_command_over_checkpoints_and_drawing_files(tmp_path, debug_store):
    for seed in (0, 1):  # trained in this process: the evaluations are what runs as a user's shell runs it
        main(["train", "--data", str(debug_store.path), "--out", str(tmp_path / f"run{seed}"), "--preset", "debug",
              "--steps", "2", "--workers", "0", "--seed", str(seed)])  # fmt: skip
    common = ("--rollouts", "2", "--max-steps", "25", "--data-dir", str(tmp_path / "data"))
    out = _bpp(
        *("eval", str(tmp_path / "run0"), str(tmp_path / "run1"), "--tasks", str(debug_store.path)),
        *("--num-tasks", "2", "--workers", "1", "--out", str(tmp_path / "eval"), *common),
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "mean ± std over checkpoints" in (tmp_path / "eval" / "summary.md").read_text()
    # `bpp draw rollout` of such a run: tests/test_bpp.py::test_rollout_command_writes_pictures
    drawing = tmp_path / "tri.json"
    drawing.write_text('{"drawings": [{"id": "tri", "strokes": [[[0.2, 0.2], [0.8, 0.2], [0.5, 0.8], [0.2, 0.2]]]}]}')
    out = _bpp("eval", str(tmp_path / "run0"), "--files", str(drawing), "--out", str(tmp_path / "mine"), *common)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "drawings: tri.json" in (tmp_path / "mine" / "results.md").read_text()


def test_every_named_run_has_its_line_in_the_help_and_fields_that_hold(tmp_path):
    from bpp.runs import RUNS, SUMMARIES

    assert set(SUMMARIES) == set(RUNS) and RUNS["demo"].method == "bpp"
    listing = _bpp("run", "--help")
    assert listing.returncode == 0 and all(f"bpp run {name} " in listing.stdout for name in RUNS)
    refused = _bpp("run", "smoke", "--batch-size", "4", "--tasks-per-batch", "8")
    assert refused.returncode != 0 and "batch_size must be >= tasks_per_batch" in refused.stderr
    unknown = _bpp("run", "nope")
    assert unknown.returncode == 2 and "bpp run smoke" in unknown.stderr
    data = tmp_path / "data"
    wrong = _bpp("run", "smoke", "--obs", "nope", "--data-dir", str(data), "--run-dir", str(tmp_path / "run"))
    assert wrong.returncode != 0 and "nope" in wrong.stderr and not data.exists()  # refused before any data is made


def test_the_thread_plan_takes_every_core_for_a_whole_run_and_leaves_the_count_to_omp_num_threads(monkeypatch):
    assert RUNS["demo"].threads == -1 and RUNS["smoke"].threads == 0  # the main job runs alone; others leave a core
    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    plan = {n: cpu_plan(TrainConfig(data="", threads=n, workers=0), cpu)[1] for n in (-1, 0, 3)}
    assert plan == {-1: usable_cores(), 0: max(1, usable_cores() - 1), 3: 3}
    assert cpu_plan(TrainConfig(data="", threads=-1, workers=1), cpu) == (1, max(1, usable_cores() - 1))
    assert cpu_plan(TrainConfig(data="", threads=-1, workers=0), gpu)[1] == 0  # torch's own count beside a GPU
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    # torch's default count then takes OMP_NUM_THREADS
    assert cpu_plan(TrainConfig(data="", threads=-1, workers=0), cpu)[1] == 0
    assert cpu_plan(TrainConfig(data="", threads=3, workers=0), cpu)[1] == 3
