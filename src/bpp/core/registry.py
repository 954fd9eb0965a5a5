"""Benchmarks by name. Adding a benchmark is a new folder under ``bpp/benchmarks/`` plus one line in :data:`BENCHMARKS`.

The contract a benchmark satisfies is :class:`bpp.core.contract.Benchmark`. Packages outside bpp can add
benchmarks through the ``bpp.benchmarks`` entry-point group (``name = "package.module:OBJECT"``), and code (e.g. a
test) through :func:`register_benchmark`.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from pathlib import Path

from bpp.core.contract import Benchmark, CommandTable
from bpp.data.integrity import read_header
from bpp.data.store import EpisodeStore
from bpp.errors import UserError

BENCHMARKS: dict[str, str] = {
    "drawanything": "bpp.benchmarks.draw.benchmark:BENCHMARK",
    "libero_gen": "bpp.benchmarks.libero.benchmark:BENCHMARK",
    "lerobot_dataset": "bpp.benchmarks.lerobot.benchmark:BENCHMARK",
    "iphumi": "bpp.benchmarks.iphumi.benchmark:BENCHMARK",
    "draw3d": "bpp.benchmarks.draw3d.benchmark:BENCHMARK",
}
"""Benchmark name (as stored in every store) -> ``module:object`` implementing the contract."""

DEFAULT_BENCHMARK = "drawanything"
"""The benchmark of the main job (``bpp demo``)."""

RESERVED_COMMANDS = ("train", "eval", "store", "demo", "run", "studio", "serve", "robot-client")
"""The generic command-line groups a benchmark's `command` may not take."""

_LOADED: dict[str, Benchmark] = {}


def register_benchmark(name: str, target: str | Benchmark) -> None:
    """Add (or replace) benchmark `name`: a ``module:object`` path or the object itself."""
    if isinstance(target, str):
        BENCHMARKS[name] = target
        _LOADED.pop(name, None)
    else:
        _check(name, target)
        BENCHMARKS[name] = f"{type(target).__module__}:<object>"
        _LOADED[name] = target


def _plugins() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group="bpp.benchmarks")}


def benchmark_names() -> list[str]:
    return sorted({*BENCHMARKS, *_plugins()})


def get_benchmark(name: str) -> Benchmark:
    """The benchmark registered as `name`; a clear error naming the registered ones otherwise."""
    if name in _LOADED:
        return _LOADED[name]
    target = BENCHMARKS.get(name) or _plugins().get(name)
    if target is None or ":" not in target or target.endswith(":<object>"):
        raise UserError(f"unknown benchmark {name!r}; registered: {', '.join(benchmark_names())}")
    module, attr = target.split(":", 1)
    benchmark = getattr(importlib.import_module(module), attr)
    _check(name, benchmark)
    _LOADED[name] = benchmark
    return benchmark


def derived_keys(name: str) -> Mapping[str, tuple[str, tuple[int, ...]]]:
    """The derived per-step keys of the benchmark registered as `name` (:attr:`Benchmark.derived_keys`); none for a
    name nothing is registered as (a store of a benchmark this install lacks shows its stored keys only)."""
    if name not in _LOADED and name not in BENCHMARKS and name not in _plugins():
        return {}
    return get_benchmark(name).derived_keys


def open_store(path: str | Path) -> EpisodeStore:
    """The store at `path` as its benchmark presents it: with the derived keys of the benchmark its header names
    (:func:`derived_keys`), so that every process that opens a store this way sees the same per-step keys."""
    return EpisodeStore(path, derived_keys(str(read_header(path).get("benchmark", ""))))


def benchmark_commands(benchmark: Benchmark) -> CommandTable:
    """`benchmark`'s own commands (``bpp <its command> <name> ...``): the table its ``command_table`` names."""
    if not benchmark.command_table:
        return {}
    module, attr = benchmark.command_table.split(":", 1)
    return getattr(importlib.import_module(module), attr)


def benchmark_for_command(command: str) -> Benchmark | None:
    """The benchmark whose command-line group is `command` (``bpp <command> ...``), if any."""
    found = [b for b in map(get_benchmark, benchmark_names()) if b.command == command]
    if len(found) > 1:
        raise ValueError(f"benchmarks {', '.join(b.name for b in found)} all take the command {command!r}")
    return found[0] if found else None


def _check(name: str, benchmark) -> None:
    if not isinstance(benchmark, Benchmark):
        members = {*Benchmark.__annotations__, *(k for k, v in vars(Benchmark).items() if callable(v) and k[0] != "_")}
        missing = sorted(a for a in members if not hasattr(benchmark, a))
        raise TypeError(f"benchmark {name!r} does not satisfy bpp.core.contract.Benchmark; missing {missing}")
    if benchmark.name != name:
        raise ValueError(f"benchmark registered as {name!r} calls itself {benchmark.name!r}")
    for key, (source, features) in benchmark.derived_keys.items():
        if not isinstance(source, str) or not features or not all(isinstance(i, int) and i >= 0 for i in features):
            raise ValueError(
                f"benchmark {name!r}: derived key {key!r} must be (a stored key, a non-empty tuple of feature indices "
                f">= 0), got {(source, features)!r}"
            )
    if benchmark.command_table and ":" not in benchmark.command_table:
        raise ValueError(
            f"benchmark {name!r}: command_table must be 'module:attribute', got {benchmark.command_table!r}"
        )
    if benchmark.command in RESERVED_COMMANDS:
        raise ValueError(f"benchmark {name!r} takes the command {benchmark.command!r}, which bpp reserves")
