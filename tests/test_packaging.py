"""The core package works without its optional extras, and a command that needs a missing extra names it."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXTRA_MODULES = {
    "studio": ["fastapi", "uvicorn", "httpx", "starlette", "pydantic"],
    "language": ["transformers"],
    "libero": ["libero", "robosuite", "mujoco", "h5py"],
    "dev": ["pytest", "playwright", "ruff"],
    "docs": ["mkdocs", "material"],
    "serve": ["websockets", "msgpack"],
    "lerobot": ["lerobot", "av", "datasets", "torchvision"],
    "iphumi": ["cv2"],
    "ray": ["ray"],
}


def _without_extras(code: str, tmp_path: Path) -> subprocess.CompletedProcess:
    """Run `code` in a fresh interpreter where no module of any extra can be imported, as after `pip install bpp`."""
    blocked = sorted(m for modules in EXTRA_MODULES.values() for m in modules)
    prelude = f"""
        import sys
        for name in {blocked!r}:  # as if not installed: importing fails, importlib.util.find_spec gives None
            sys.modules[name] = None
    """
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent(prelude) + textwrap.dedent(code))
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, timeout=300)


def test_the_core_commands_load_without_any_extra(tmp_path):
    result = _without_extras(
        """
        from bpp.cli import main
        for argv in (["--help"], ["draw", "generate", "--help"], ["train", "--help"], ["eval", "--help"]):
            try:
                main(argv)
            except SystemExit as exit:
                assert exit.code in (0, None), (argv, exit.code)
        import bpp.benchmarks.libero.benchmark  # registered, and importable, without LIBERO itself
        print("ok")
        """,
        tmp_path,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")


@pytest.mark.parametrize(
    ("argv", "extra"),
    [
        (["studio", "--no-browser", "--runs", "runs"], "studio"),
        (["libero", "tasks", "--out", "tasks"], "libero"),
        (["serve", "runs/none"], "serve"),
        (["lerobot", "import", ".", "--out", "x.zarr"], "lerobot"),
    ],
)
def test_a_command_needing_a_missing_extra_says_which_in_one_line(tmp_path, argv, extra):
    result = _without_extras(f"from bpp.cli import main\nmain({argv!r})\n", tmp_path)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    assert f"bpp[{extra}]" in result.stderr or f".[{extra}]" in result.stderr, result.stderr[-3000:]


OWN_ENVIRONMENT = {"lerobot"}
"""Extras left out of `all`: LeRobot pins torch < 2.11, so it has an environment of its own (.venv-lerobot)."""


def test_the_extras_declare_what_the_tests_block():
    """The modules blocked above are those of the extras pyproject.toml declares (so the test above means something);
    `all` is every one of them but those with an environment of their own."""
    tomllib = pytest.importorskip("tomllib", reason="needs Python 3.11's tomllib")
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(EXTRA_MODULES) <= set(extras)
    shared = sorted(set(EXTRA_MODULES) - OWN_ENVIRONMENT, key=list(extras).index)
    assert extras["all"] == [f"bpp[{','.join(shared)}]"]
