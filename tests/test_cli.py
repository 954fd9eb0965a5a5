import subprocess
import sys

from bpp.data.store import EpisodeStore


def _bpp(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "bpp.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def test_help_lists_commands():
    out = _bpp("--help")
    assert out.returncode == 0 and "bpp draw generate" in out.stdout
    assert _bpp("frobnicate").returncode == 2


def test_generate_sheet_video_info(tmp_path):
    store = tmp_path / "d.zarr"
    out = _bpp("draw", "generate", "--preset", "debug", "--num-tasks", "4", "--out", str(store), "--workers", "2")
    assert out.returncode == 0, out.stderr
    assert EpisodeStore(store).num_tasks == 4
    again = _bpp("draw", "generate", "--preset", "debug", "--out", str(store))
    assert again.returncode != 0 and "already exists" in again.stderr
    assert _bpp("draw", "sheet", str(store), "--out", str(tmp_path / "s.png"), "--tasks", "2").returncode == 0
    assert (tmp_path / "s.png").stat().st_size > 10_000
    assert _bpp("draw", "video", str(store), "--episode", "1", "--out", str(tmp_path / "v.gif")).returncode == 0
    assert (tmp_path / "v.gif").stat().st_size > 10_000
    assert _bpp("draw", "video", str(store), "--out", str(tmp_path / "v.mp4")).returncode == 0
    assert (tmp_path / "v.mp4").stat().st_size > 2_000
    info = _bpp("store", "info", str(store))
    assert info.returncode == 0 and "episodes=12" in info.stdout


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
    out = _bpp("draw", "generate", "--preset", "nope", "--out", str(tmp_path / "x.zarr"))
    assert out.returncode != 0 and "unknown preset" in out.stderr
    out = _bpp("store", "info", str(tmp_path))
    assert out.returncode != 0 and "not an episode store" in out.stderr


def test_demo_main_job_runs_and_reuses(tmp_path):
    args = ("demo", "--out-dir", str(tmp_path / "out"), "--data-dir", str(tmp_path / "data"), "--num-tasks", "6")
    first = _bpp(*args)
    assert first.returncode == 0, first.stderr
    for name in ("train_sheet.png", "human_sheet.png", "human_demo_0.gif"):
        assert (tmp_path / "out" / name).stat().st_size > 10_000
    second = _bpp(*args)
    assert second.returncode == 0 and second.stdout.count("reusing") == 2
