"""Each extra brings what bpp imports from it: every module bpp's source imports (at the top of a module or inside a
function) from a distribution an extra adds to the core imports in a process that sees only the core's and that
extra's installed distributions, followed through their own requirements (the versions of this environment, not a
fresh resolve). A requirement missing from bpp's lists, or from a dependency's own (an upstream package that forgets
one of its imports), fails here instead of on a user's machine."""

from __future__ import annotations

import ast
import importlib.metadata as metadata
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest
from packaging.utils import canonicalize_name

from core_only import core_closure
from helpers import REQUIRE_ALL

SRC = Path(__file__).parents[1] / "src" / "bpp"
EXTRAS = ("studio", "serve", "language", "libero", "iphumi", "ray", "draw3d")
"""The extras `all` holds that bpp's source imports from (dev and docs are the tests' and the docs' own); lerobot has
an environment of its own (tests/test_lerobot_install.py)."""

ELSEWHERE = {"lerobot", "av", "datasets", "pyarrow", "openpi_client"}
"""Modules of environments other than this one: LeRobot's (the lerobot extra, LeRobot's own requirements) and the
robot computer's (openpi's client, requirements-robot.lock); their tests install and import them there."""

ALONE = ("studio", "language", "libero")
"""The extras checked here in isolation; each of the others is a guide's recipe of its own (`pip install -e .[ray]`),
installed for real into a new environment by tests/test_install_recipes.py."""


@cache
def _distributions() -> dict[str, list[str]]:
    return metadata.packages_distributions()


@cache
def imported_modules() -> frozenset[str]:
    """Every module bpp's source imports by absolute name that is neither bpp's nor the standard library's."""
    found = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module)
    return frozenset(m for m in found if m.partition(".")[0] not in {"bpp", *sys.stdlib_module_names})


def providers(module: str) -> set[str]:
    """The installed distributions that provide `module`'s top-level package (canonical names)."""
    return {canonicalize_name(d) for d in _distributions().get(module.partition(".")[0], [])}


def test_every_extra_bpp_declares_is_checked_here_or_in_its_own_environment():
    declared = set(metadata.metadata("bpp").get_all("Provides-Extra"))
    assert declared == {*EXTRAS, "dev", "docs", "all", "lerobot"}


def test_every_third_party_module_bpp_imports_comes_from_the_core_or_one_extra():
    core = core_closure()
    reachable = set(core).union(*(core_closure("bpp", (extra,)) for extra in (*EXTRAS, "lerobot")))
    # Outside `make test` (which installs every extra) a module of an extra not installed here cannot be looked up.
    unknown = set() if REQUIRE_ALL else {m for m in imported_modules() if not providers(m)}
    undeclared = sorted(
        m for m in imported_modules() - unknown if not providers(m) & reachable and m.partition(".")[0] not in ELSEWHERE
    )
    assert not undeclared, f"imported by bpp but brought by no requirement of the core or of an extra: {undeclared}"
    assert "fastapi" in imported_modules() and "torch" in imported_modules()  # the scan sees both kinds of import


@pytest.mark.slow
@pytest.mark.parametrize(
    "extra",
    [pytest.param(e, marks=getattr(pytest.mark, e)) for e in ALONE],
)
def test_an_extra_alone_brings_every_module_bpp_imports_from_it(extra):
    core, closure = core_closure(), core_closure("bpp", (extra,))
    modules = sorted(m for m in imported_modules() if providers(m) & (closure - core))
    assert modules, f"bpp imports nothing the {extra} extra brings"
    script = Path(__file__).with_name("core_only.py")
    done = subprocess.run(
        [sys.executable, str(script), "--import", extra, *modules], capture_output=True, text=True, timeout=240
    )
    assert done.returncode == 0, f"with the core and {extra} only, importing {modules}:\n{done.stderr[-3000:]}"
