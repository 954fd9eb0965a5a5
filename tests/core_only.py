"""Run ``bpp`` as if only the core package were installed (``pip install -e .``, what ``make demo`` installs), in an
environment that has every extra: a module of a distribution outside the core's requirements, followed through
their own requirements, cannot be imported. ``python tests/core_only.py demo ...`` is ``bpp demo ...`` so restricted.

A full install of the core alone into a new environment takes minutes and gigabytes (torch and its CUDA wheels);
this checks the same thing the imports decide: that what the core command runs imports nothing an extra brings.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.metadata as metadata
import sys

from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


def core_closure(root: str = "bpp") -> set[str]:
    """The distributions `root` needs without extras, and theirs, transitively (canonical names)."""
    environment = {**default_environment(), "extra": ""}
    seen, todo = set(), [root]
    while todo:
        name = canonicalize_name(todo.pop())
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue  # a requirement whose marker holds here but that is not installed: nothing to follow
        for line in requires:
            requirement = Requirement(line)
            if requirement.marker is None or requirement.marker.evaluate(environment):
                todo.append(requirement.name)
    return seen


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
            print(f"[core-only] not found: {name}", file=sys.stderr)
            return None
        return self.finder.find_spec(name, path, target)

    def find_distributions(self, *args, **kwargs):
        """Installed distributions' metadata (``importlib.metadata``), without those outside the core."""
        for dist in self.finder.find_distributions(*args, **kwargs):
            if canonicalize_name(dist.metadata["Name"]) in self.allowed:
                yield dist

    def invalidate_caches(self):
        self.finder.invalidate_caches()


def install() -> None:
    """Put the restricted finder in place of Python's path finder."""
    finder = next(f for f in sys.meta_path if f is importlib.machinery.PathFinder)
    sys.meta_path[sys.meta_path.index(finder)] = OutsideCore(core_closure(), finder)


if __name__ == "__main__":
    install()
    from bpp.cli import main

    sys.exit(main(sys.argv[1:]))
