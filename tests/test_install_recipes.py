"""Install recipes the README and the guides give, checked as a new environment would run them.

The robot computer's recipe is installed as written into a new virtual environment: a recipe that works only beside
what another environment brought fails here (openpi's client imports ``typing_extensions`` without requiring it, and
the robot environment `make test` builds has it from other packages). So is every recipe that installs bpp, by uv,
whose cache links the same wheels into each new environment (seconds, where pip would copy gigabytes of torch per
recipe): it must bring exactly the distributions tests/test_extras.py checks that extra with, and the modules bpp
imports from them must import; from the ranges alone it must resolve too. `make test` builds the environments of the
other two (`.[all]`: .venv; `.[lerobot]`: .venv-lerobot) for real. Needs the package index, as any install does; the
first run fills uv's cache (6.1 GB)."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import venv
from functools import cache
from pathlib import Path

import pytest
from packaging.utils import canonicalize_name

from core_only import core_closure
from helpers import OPTIONAL_PARTS
from test_extras import ALONE, EXTRAS, imported_modules, providers

ROOT = Path(__file__).resolve().parents[1]
GUIDES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
UV = Path(sys.executable).with_name("uv")
"""uv, from the dev extra."""
BUILT_BY_MAKE = {("all",), ("lerobot",)}
"""Recipes whose environments `make test` builds (.venv, .venv-lerobot)."""
PLATFORM = ["--python-version", "3.11.7", "--python-platform", "x86_64-manylinux_2_28"]
"""The platform the locks are for (Makefile, `make lock`)."""
ELSEWHERE = {
    ("lerobot",): "tests/test_lerobot_install.py",
    ("openpi-client", "typing_extensions"): "the robot computer's recipe test, in this module",
}
"""Recipes of other projects' packages the guides give, and what installs them for real."""


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


@cache
def documented_recipes() -> tuple[tuple[str, tuple[str, ...]], ...]:
    """Every ``pip install`` the README and the guides give: (where, its arguments), an elided ``...`` left out."""
    found = []
    for path in GUIDES:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            for command in re.findall(r"pip install ([^`#\n]+)", line):
                arguments = tuple(shlex.split(command))
                if "..." not in arguments:
                    found.append((f"{path.relative_to(ROOT)}:{number}", arguments))
    return tuple(found)


def targets(arguments: tuple[str, ...]) -> list[str]:
    """What a recipe installs: its arguments that are neither options nor an option's file (`-c requirements.lock`)."""
    files = {i + 1 for i, argument in enumerate(arguments) if argument in ("-c", "--constraint", "-r")}
    return [a for i, a in enumerate(arguments) if not a.startswith("-") and i not in files]


def bpp_extras(target: str) -> tuple[str, ...] | None:
    """The extras a target installs bpp from the clone with (``.`` or ``.[a,b]``), or None for another target."""
    found = re.fullmatch(r"\.(?:\[([a-z0-9,]+)\])?", target)
    return None if found is None else tuple(sorted(filter(None, (found.group(1) or "").split(","))))


def resolve(extras: tuple[str, ...], constraints: str | None, *more: str) -> dict[str, str]:
    """What uv installs into an empty environment for bpp with `extras` (and `more` requirements): name -> version."""
    command = [str(UV), "pip", "compile", "pyproject.toml", *PLATFORM, "--no-header", "--no-annotate", "--quiet"]
    command += [f"--extra={extra}" for extra in extras] + (["-c", constraints] if constraints else [])
    if more:
        command += ["-"]
    done = subprocess.run(command, cwd=ROOT, input="\n".join(more), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{' '.join(command)}:\n{done.stderr[-3000:]}"
    pins = (line.split("==") for line in done.stdout.splitlines() if "==" in line)
    return {canonicalize_name(name): version.strip() for name, version in pins}


def bpp_recipes() -> list[tuple[str, ...]]:
    return sorted({bpp_extras(t) for _, args in documented_recipes() for t in targets(args)} - {None})


def test_the_guides_recipes_are_found_and_each_is_checked_somewhere():
    assert {(), ("language", "studio"), ("all",), ("lerobot",), ("ray",)} <= set(bpp_recipes()), bpp_recipes()
    others = {tuple(targets(args)) for _, args in documented_recipes()}
    others = {t for t in others if len(t) != 1 or bpp_extras(t[0]) is None}
    assert others <= set(ELSEWHERE), f"recipes no test installs: {sorted(others - set(ELSEWHERE))}"
    alone = {recipe[0] for recipe in bpp_recipes() if len(recipe) == 1 and recipe not in BUILT_BY_MAKE}
    assert set(EXTRAS) <= alone | set(ALONE), f"extras checked neither alone nor by a recipe: {set(EXTRAS) - alone}"


def test_no_guide_or_message_installs_bpp_from_the_package_index():
    # bpp is installed from its clone; a package of that name on the index is another project's.
    wrong = [where for where, args in documented_recipes() for t in targets(args) if re.match(r"bpp\b", t)]
    for path in sorted((ROOT / "src" / "bpp").rglob("*.py")):  # errors and --help
        text = path.read_text()
        wrong += [f"{path.relative_to(ROOT)}: {m}" for m in re.findall(r"pip install ['\"]?bpp\b[^\s'\"]*", text)]
    assert not wrong, f"these install the index's bpp, not this one: {wrong}"


PARTS = {"all": ("studio", "serve", "language", "libero", "iphumi", "ray"), "draw3d": ("libero", "iphumi")}
"""The extras that name other extras: the markers of optional parts (tests/helpers.py) their check needs."""


def needs(extras: tuple[str, ...]) -> list[pytest.MarkDecorator]:
    parts = {part for extra in extras for part in PARTS.get(extra, (extra,))}
    return [getattr(pytest.mark, part) for part in sorted(parts) if part in OPTIONAL_PARTS]


def uv(*arguments: str) -> str:
    done = subprocess.run([str(UV), *arguments], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"uv {' '.join(arguments)}:\n{done.stderr[-3000:]}"
    return done.stdout


@pytest.mark.slow
@pytest.mark.parametrize(
    "extras",
    [pytest.param(e, id=",".join(e) or "core", marks=needs(e)) for e in bpp_recipes() if e not in BUILT_BY_MAKE],
)
def test_a_recipe_installs_into_a_new_environment_and_what_bpp_imports_from_it_imports(extras, tmp_path):
    where = tmp_path / "env"
    uv("venv", "--quiet", str(where), "--python", sys.executable)
    python = str(where / "bin" / "python")
    target = f".[{','.join(extras)}]" if extras else "."
    uv("pip", "install", "--quiet", "--python", python, "-c", "requirements.lock", "-e", target)
    installed = {
        canonicalize_name(d["name"]) for d in json.loads(uv("pip", "list", "--format=json", "--python", python))
    }
    closure, core = core_closure("bpp", extras), core_closure()
    assert installed - {"bpp"} == closure - {"bpp"}, (
        f"{target} installs {sorted(installed - closure)} that tests/test_extras.py does not see, and it sees "
        f"{sorted(closure - installed - {'bpp'})} that the recipe does not install"
    )
    own = closure - core if extras else core
    modules = sorted(m for m in imported_modules() if providers(m) & own)
    assert modules, f"bpp imports nothing {target} brings"
    script = "; ".join(f"import {m}" for m in (*modules, "bpp.cli"))
    ran = subprocess.run([python, "-c", script], capture_output=True, text=True, timeout=300)
    assert ran.returncode == 0, f"in a new environment with {target}: {script}\n{ran.stderr[-3000:]}"
    assert resolve(extras, None), "the declared ranges resolve to nothing"


@pytest.mark.slow
@pytest.mark.parametrize("extras", [pytest.param(("all",), marks=needs(("all",)))])
def test_every_extra_of_the_all_recipe_resolves_to_what_its_environment_holds(extras):
    locked = resolve(extras, "requirements.lock")
    assert set(locked) == core_closure("bpp", extras) - {"bpp"}


@pytest.mark.slow
def test_the_lerobot_recipe_resolves_beside_lerobot_at_its_lock():
    # The guide installs LeRobot first, then bpp's extra on top; their environment is built for real by `make test`.
    resolved = resolve(("lerobot",), "requirements-lerobot.lock", "lerobot")
    assert resolved["lerobot"].startswith("0.4") and int(resolved["torch"].split(".")[1]) < 11
