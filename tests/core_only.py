"""Run ``bpp`` as if only the core package were installed (``pip install -e .``, what ``make demo`` installs), in an
environment that has every extra: a module of a distribution outside the core's requirements, followed through
their own requirements, cannot be imported. ``python tests/core_only.py demo ...`` is ``bpp demo ...`` so restricted.

A full install of the core alone into a new environment takes minutes and gigabytes (torch and its CUDA wheels);
this checks the same thing the imports decide: that what the core command runs imports nothing an extra brings.
``python tests/core_only.py --import EXTRA MODULE ...`` imports the modules with the core and one extra visible, as
``pip install .[EXTRA]`` would have installed them (tests/test_extras.py).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.metadata as metadata
import site
import sys
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

SITES = [Path(p).resolve() for p in (*site.getsitepackages(), site.getusersitepackages())]
"""The folders installed distributions' top-level modules live in."""


def vendored(folder: str) -> bool:
    """Whether `folder` lies inside an installed package (``site-packages/ray/thirdparty_files``): the copies of other
    packages it holds are that package's own, as pip installed it. Not a site folder itself, nor a folder elsewhere
    (a source checkout, PYTHONPATH)."""
    path = Path(folder).resolve()
    return any(path != site and path.is_relative_to(site) for site in SITES)


def core_closure(root: str = "bpp", extras: tuple[str, ...] = ()) -> set[str]:
    """The distributions `root` needs with its `extras` (none: the core), and theirs, transitively, extras named in
    a requirement (``bpp[libero,iphumi]``) followed too (canonical names)."""
    seen, todo = set(), [(root, frozenset(extras))]
    while todo:
        name, wanted = todo.pop()
        name = canonicalize_name(name)
        if (name, wanted) in seen:
            continue
        seen.add((name, wanted))
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue  # a requirement whose marker holds here but that is not installed: nothing to follow
        for line in requires:
            requirement = Requirement(line)
            holds = requirement.marker is None or any(
                requirement.marker.evaluate({**default_environment(), "extra": extra}) for extra in ("", *wanted)
            )
            if holds:
                todo.append((requirement.name, frozenset(requirement.extras)))
    return {name for name, _ in seen}


class OutsideCore(importlib.abc.MetaPathFinder):
    """Python's path finder, blind to top-level modules that only distributions outside the core provide: they are
    not found, as if not installed (a probe such as ``importlib.util.find_spec`` answers None, an import fails)."""

    def __init__(self, allowed: set[str], finder):
        self.finder, self.allowed = finder, allowed
        owners = metadata.packages_distributions()
        self.refused = {
            module
            for module, dists in owners.items()
            if not any(canonicalize_name(d) in allowed for d in dists) and module not in sys.stdlib_module_names
        }

    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in self.refused:
            # A copy a package ships inside itself and puts on sys.path (Ray's vendored psutil) is its own.
            elsewhere = [p for p in (sys.path if path is None else path) if vendored(p)]
            spec = self.finder.find_spec(name, elsewhere, target)
            if spec is None:
                print(f"[core-only] not found: {name}", file=sys.stderr)
            return spec
        return self.finder.find_spec(name, path, target)

    def find_distributions(self, *args, **kwargs):
        """Installed distributions' metadata (``importlib.metadata``), without those outside the core."""
        for dist in self.finder.find_distributions(*args, **kwargs):
            if canonicalize_name(dist.metadata["Name"]) in self.allowed:
                yield dist

    def invalidate_caches(self):
        self.finder.invalidate_caches()


def install(extras: tuple[str, ...] = ()) -> None:
    """Put the restricted finder in place of Python's path finder, so that only the core's and `extras`' distributions
    are seen."""
    finder = next(f for f in sys.meta_path if f is importlib.machinery.PathFinder)
    sys.meta_path[sys.meta_path.index(finder)] = OutsideCore(core_closure("bpp", extras), finder)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--import"]:  # --import EXTRA MODULE ...: import each module with the core and EXTRA only
        install((sys.argv[2],))
        for module in sys.argv[3:]:
            importlib.import_module(module)
        sys.exit(0)
    install()
    from bpp.cli import main

    sys.exit(main(sys.argv[1:]))
