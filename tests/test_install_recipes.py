"""Install recipes the guides give, run as written in a new virtual environment: a recipe that works only beside
what another environment brought fails here (openpi's client imports ``typing_extensions`` without requiring it, and
the robot environment `make test` builds has it from other packages). Needs the package index, as any install does;
versions follow the lock the tests were measured with."""

from __future__ import annotations

import re
import subprocess
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def robot_recipe() -> tuple[list[str], str]:
    """The robot computer's recipe in the serving guide: the packages its ``pip install`` names, and the import lines
    of the robot loop it shows."""
    section = (ROOT / "docs" / "serving.md").read_text().split("## A robot's loop", 1)[1]
    command = re.search(r"`pip install ([^`]+)`", section)
    assert command, "the serving guide's robot loop names no pip install"
    code = section.split("```python", 1)[1].split("```", 1)[0]
    imports = [line for line in code.splitlines() if re.match(r"(from \S+ )?import ", line)]
    assert imports, "the serving guide's robot loop imports nothing"
    return command.group(1).split(), "\n".join(imports)


@pytest.mark.slow
def test_the_robot_computers_recipe_runs_the_loop_s_imports_in_a_new_environment(tmp_path):
    packages, imports = robot_recipe()
    venv.create(tmp_path / "robot", with_pip=True)
    python = str(tmp_path / "robot" / "bin" / "python")
    lock = str(ROOT / "requirements-robot.lock")
    install = [python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "-c", lock, *packages]
    done = subprocess.run(install, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    ran = subprocess.run([python, "-c", imports], capture_output=True, text=True, timeout=120)
    assert ran.returncode == 0, f"{imports}\n{ran.stderr[-2000:]}"
    check = "import importlib.util as u; print([m for m in ('torch', 'bpp') if u.find_spec(m)])"
    assert subprocess.run([python, "-c", check], capture_output=True, text=True).stdout.strip() == "[]"
