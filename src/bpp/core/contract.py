"""The benchmark contract: what a benchmark provides so that the generic layers (data, policies, training,
evaluation, the command line) can use it without importing it.

A benchmark is one folder ``bpp/benchmarks/<name>/`` whose module-level object satisfies :class:`Benchmark`, plus
one line in :data:`bpp.core.registry.BENCHMARKS` (or a ``bpp.benchmarks`` entry point, or
:func:`bpp.core.registry.register_benchmark` at run time). Everything else reaches it through the registry: a
store names its benchmark, and a checkpoint names the store it was trained on.

The generic evaluation protocol (:mod:`bpp.evaluation.evaluate`) calls, for each task of a task set:

1. :meth:`Benchmark.rollout_conditions` once per rollout, with that rollout's own generator, for whatever varies
   between rollouts besides the seed (a board angle, an initial scene);
2. ``agent.reset_batch`` with each rollout's task context (built by :func:`bpp.data.contexts.task_context` from the
   prompt demonstration, using :meth:`Benchmark.frames` for cameras);
3. :meth:`Benchmark.run_rollouts`, which steps the benchmark's environments in lockstep with ``agent.act_batch``
   and scores each rollout with the benchmark's :class:`Metric`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from bpp.data.spec import ObservationPreset
from bpp.data.store import EpisodeStore
from bpp.errors import UserError


@dataclass(frozen=True)
class Metric:
    """How a rollout is scored: ``score`` is what the protocol averages (per task, then over tasks)."""

    name: str
    """e.g. "distance to target" or "success"."""
    unit: str = ""
    """e.g. "px" ("" for rates)."""
    lower_is_better: bool = True
    good_threshold: float | None = None
    """A rollout is *good* when its score is under this (lower is better) or at least this (higher is better); the
    share of good rollouts is reported (e.g. a distance under 5 px; success = 1)."""
    description: str = ""
    """One sentence for reports: what a rollout's score is."""

    def good(self, scores: np.ndarray) -> np.ndarray:
        """Boolean mask of good rollouts (all False without a threshold)."""
        scores = np.asarray(scores, dtype=float)
        if self.good_threshold is None:
            return np.zeros(scores.shape, dtype=bool)
        return scores < self.good_threshold if self.lower_is_better else scores >= self.good_threshold

    @property
    def good_label(self) -> str:
        if self.good_threshold is None:
            return ""
        relation = "under" if self.lower_is_better else "at least"
        return f"rollouts {relation} {self.good_threshold:g}{self._unit}"

    def format(self, value: float) -> str:
        return f"{value:.2f}{self._unit}"

    @property
    def _unit(self) -> str:
        return f" {self.unit}" if self.unit else ""


@dataclass
class RolloutResult:
    """One scored rollout, as a benchmark's runner returns it."""

    score: float
    """The metric's per-rollout score (e.g. the best distance to the target reached; 1 a success, 0 a failure)."""
    steps: int
    """Environment steps taken."""
    extra: dict = field(default_factory=dict)
    """Other JSON-able numbers recorded per rollout (e.g. the final distance)."""
    frames: list = field(default_factory=list, repr=False)
    """RGB frames (H, W, 3) uint8 if recorded; the last one shows the outcome (the report's grid)."""


@dataclass(frozen=True)
class TaskSet:
    """Tasks to evaluate on: a store and a label for reports."""

    store: EpisodeStore
    label: str


CommandTable = Mapping[str, tuple[type, Callable[[Any], None]]]
"""``{name: (tyro dataclass, function)}``: a benchmark's own commands, ``bpp <command> <name> ...``."""


def frames_to_record(entry: bool | str) -> str:
    """``"all"``, ``"last"`` or ``""`` (none) for an entry of :meth:`Benchmark.run_rollouts`'s `record_frames`."""
    if entry is True:
        return "all"
    if entry in (False, None, "", "all", "last"):
        return entry or ""
    raise ValueError(f"record_frames entries are True, False, 'all' or 'last', not {entry!r}")


@runtime_checkable
class Benchmark(Protocol):
    """What a benchmark provides. See the module docstring for how the protocol uses it."""

    name: str
    """Written into every store it generates (``store.benchmark``); the registry's key."""
    command: str
    """Its command-line group: ``bpp <command> generate ...`` (e.g. ``draw``)."""
    description: str

    # ------------------------------------------------------------------ data
    data_config: type
    """The frozen dataclass :meth:`generate` takes (its fields become ``bpp <command> generate`` flags)."""
    data_presets: Mapping[str, Any]
    """Named data configurations (at least ``debug``)."""
    default_data_dir: Path
    """Where named task sets and stores built from files go by default."""

    def generate(self, cfg: Any, out: Path, *, workers: Any = 0, overwrite: bool = False, progress: bool = True):
        """Generate tasks and demonstrations into a new store at `out` (atomically); returns the EpisodeStore.
        `workers`: a number of local processes (0: one per core) or a :class:`bpp.executor.Executor` (``bpp ...
        generate --executor ray`` passes a Ray cluster's); :func:`bpp.executor.as_executor` takes either."""
        ...

    def frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """Camera `key`'s observations of a stored episode, (T, size, size, 3) uint8; with `last_only`, the last one
        (1, ...); with `steps` (k,) (step indices within the episode, any order), those (k, ...), made without the
        others where the benchmark can (a batch needs a few frames of each episode). Raise ValueError if the
        benchmark has no such camera."""
        ...

    derived_keys: Mapping[str, tuple[str, tuple[int, ...]]]
    """Per-step keys the benchmark's stores present without storing them: key -> (stored key, feature indices), each
    some features of a stored key in the order given (e.g. the gripper's pose out of a robot's whole proprioception;
    ``{}`` for none). A store opened with them reads and normalises them like stored keys
    (:attr:`bpp.data.store.EpisodeStore.derived`; :func:`bpp.core.registry.open_store` opens a store with those of
    the benchmark it names), so stores written before a key was declared have it too;
    :func:`bpp.data.store.with_derived` adds them to a rollout's observations the same way."""

    # ---------------------------------------------------------- observations
    observations: Mapping[str, ObservationPreset]
    """Named observation/action settings (``bpp train --obs NAME``)."""

    def default_observation(self, size: str) -> str:
        """The observation preset used with a method size preset (``debug``, ``cpu``, ``paper``) when none is named."""
        ...

    # ------------------------------------------------------------ evaluation
    metric: Metric
    max_steps: int
    """Default rollout length limit."""
    task_sets: Mapping[str, str]
    """Named task sets besides ``train`` and store paths: name -> description (e.g. ``human``)."""

    def task_set(self, name: str, data_dir: Path, workers: Any = 0) -> TaskSet:
        """A named task set's store (generated into `data_dir` on first use, over `workers`, as in :meth:`generate`)."""
        ...

    def task_set_from_files(self, files: Sequence[Path], data_dir: Path, workers: Any = 0) -> TaskSet:
        """Tasks from user files in the benchmark's own format, demonstrated by its demonstrator (over `workers`, as in
        :meth:`generate`); files are validated before anything is written. Raise ValueError if the benchmark takes no
        files."""
        ...

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        """What varies between rollouts of one task besides the seed, drawn from `rng`; JSON-able (recorded per
        rollout and passed back to :meth:`run_rollouts`)."""
        ...

    def run_rollouts(
        self,
        agent: Any,
        store: EpisodeStore,
        rollouts: Sequence[Mapping],
        max_steps: int,
        record_frames: Sequence[bool | str],
    ) -> list[RolloutResult]:
        """Run rollouts in lockstep with an agent already reset with their contexts (``agent.act_batch``).

        ``record_frames[i]`` says which frames rollout i returns (:func:`frames_to_record`): True or ``"all"`` (a
        video), ``"last"`` (its final frame alone: rendering costs as much as the physics in a 3-D scene), or False.

        rollouts[i] has ``target_episode`` (the demonstration whose task scores it), ``seed`` and the keys of
        :meth:`rollout_conditions`. Of the agent (:class:`bpp.policies.agent.PolicyAgent`) a runner uses
        ``data_spec`` (what to observe: keys, image size; which action key it outputs), ``obs_keys`` (the per-step
        keys ``act_batch`` reads) and ``act_batch({key: (B, ...)}) -> (B, A)`` while rollouts run; a finished rollout
        keeps being passed its last observation (its actions are ignored)."""
        ...

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        """An RGB picture of a stored demonstration (the report's grid shows it beside a rollout)."""
        ...

    def describe_rollout(self, row: Mapping) -> str:
        """A short caption of a rollout's conditions for pictures (e.g. "board +30°")."""
        ...

    command_table: str
    """Where the benchmark's own commands besides ``generate`` are (e.g. pictures of a store, a demo job): the
    ``module:attribute`` of a :data:`CommandTable` ("" for none), which
    :func:`bpp.core.registry.benchmark_commands` imports. Named rather than held, so that the commands module
    may import the benchmark object and not the other way round."""


def device_frames(benchmark: Benchmark, store: EpisodeStore, device):
    """The benchmark's optional renderer of `store`'s frames on `device` (a :class:`bpp.data.frame_refs.DeviceFrames`,
    for ``bpp train --frames-on device``): its ``device_frames(store, device)``, which a benchmark may provide beside
    :meth:`Benchmark.frames`. ValueError if it provides none."""
    make = getattr(benchmark, "device_frames", None)
    if make is None:
        raise UserError(
            f"benchmark {benchmark.name!r} cannot render its frames on the training device (it has no "
            "device_frames); train with --frames-on loader"
        )
    return make(store, device)
