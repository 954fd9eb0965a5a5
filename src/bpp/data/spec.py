"""What a policy reads from a store, and the named observation settings a benchmark offers.

These are plain descriptions shared by benchmarks (which declare :class:`ObservationPreset`) and methods (which
declare a :class:`DataSpec`); neither side imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from bpp.errors import UserError

ContextKind = Literal["demo", "goal_image", "instruction"]
"""What a method is conditioned on: a whole demonstration (the prompt), its final frame, or the task's text."""
CONTEXT_KINDS: tuple[str, ...] = get_args(ContextKind)


@dataclass(frozen=True)
class ObservationPreset:
    """A benchmark's named choice of what a policy observes and how it acts (the *which*; the method's size
    preset decides the *how*: encoder widths, Fourier features).

    ``bpp train --obs NAME`` combines one with a method's size preset (``--preset debug|cpu|paper``).
    """

    proprio_keys: tuple[str, ...]
    """Proprioception keys, one (dim,) entry each; a demonstration prompt can include or drop them as a group."""
    lowdim_keys: tuple[str, ...] = ()
    """Other low-dimensional observation keys, one (dim,) entry each."""
    image_keys: tuple[str, ...] = ()
    """Cameras, (image_size, image_size, 3) uint8 (empty: state-only)."""
    image_size: int = 96
    action_key: str = "action"
    """The per-step key the policy learns to output (the benchmark's env must know how to execute it)."""
    goal_camera: str = "image"
    """The camera whose final frame is a goal image (the Goal-Image baseline), whether or not the policy observes it."""
    description: str = ""

    def __post_init__(self):
        if not (self.proprio_keys or self.lowdim_keys or self.image_keys):
            raise UserError("an observation preset must observe at least one key")
        if self.image_size < 8:
            raise UserError(f"image_size must be >= 8, got {self.image_size}")


@dataclass(frozen=True)
class DataSpec:
    """What a method's training batches and task contexts contain (each model builds one: ``model.data_spec()``)."""

    lowdim_keys: tuple[str, ...]
    """Per-step low-dimensional keys (observation and proprioception), in the batch's ``obs``."""
    image_keys: tuple[str, ...] = ()
    image_size: int = 96
    action_key: str = "action"
    n_obs_steps: int = 2
    horizon: int = 16
    context: ContextKind = "demo"
    """demo: a whole demonstration (the prompt); goal_image: its final frame; instruction: the task's text."""
    context_image_key: str = "image"
    context_image_size: int = 96
    """Goal images: which camera and at what size."""
    samples: Literal["windows", "episodes"] = "windows"
    """windows: (observation history, action chunk) windows; episodes: whole demonstrations, padded (ICRT)."""
    max_prompt_steps: int = 800
    context_obs_stride: int = 1
    """A demonstration context's observations at every k-th step only (its actions stay whole): BPP reads one
    observation per prompt chunk, so training renders and sends just those (the context then says ``obs_stride``)."""
    max_episode_steps: int = 400
    """Whole-episode samples are cut to this length."""
    memory_offsets: tuple[int, ...] = ()
    """Earlier observations of the rollout itself that the policy reads before its To-step history: step offsets
    from the current step, negative and increasing (e.g. (-20, -10): the states 20 and 10 steps ago)."""

    def __post_init__(self):
        if self.context not in CONTEXT_KINDS:
            raise UserError(f"context must be one of {CONTEXT_KINDS}, got {self.context!r}")
        offsets = self.memory_offsets
        if any(o >= 1 - self.n_obs_steps for o in offsets) or list(offsets) != sorted(set(offsets)):
            raise UserError(
                f"memory_offsets must increase and lie before the {self.n_obs_steps}-step history, got {offsets}"
            )

    @property
    def obs_offsets(self) -> tuple[int, ...]:
        """Every observation the policy reads, as step offsets from the current step (0), oldest first: the
        rollout memory, then the To-step history. Before a rollout's first step, its first observation stands in."""
        return (*self.memory_offsets, *range(1 - self.n_obs_steps, 1))

    @property
    def history_length(self) -> int:
        """How many of the latest observations a rollout keeps to read :attr:`obs_offsets` from."""
        return 1 - self.obs_offsets[0]
