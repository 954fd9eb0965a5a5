"""What a training run is asked to do: :class:`TrainConfig`, optimisation and bookkeeping (the model's own
configuration is the method's Config). Imports no torch, so that the command line can offer its flags at once; the
loop that runs it is :mod:`bpp.train`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from bpp.data.spec import DataSpec
from bpp.utils import check_fields

CompileMode = Literal["off", "default", "reduce-overhead", "max-autotune-no-cudagraphs", "cudagraphs"]
"""``torch.compile``'s modes that suit training; ``cudagraphs``, its backend that records the captured graphs as CUDA
graphs without generating kernels (no Triton needed, seconds to compile); and off."""
COMPILE_MODES: tuple[str, ...] = get_args(CompileMode)
FramesOn = Literal["loader", "device"]
FRAMES_ON: tuple[str, ...] = get_args(FramesOn)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and bookkeeping (the model's own configuration is separate)."""

    data: Path
    """Training store (e.g. data/draw/train.zarr)."""
    out: Path = Path("runs/bpp")
    """Run directory: config.json, TensorBoard logs, checkpoints/."""
    method: str = "bpp"
    steps: int = 3000
    batch_size: int = 64
    """Samples per step and process."""
    tasks_per_batch: int = 1
    """G: tasks per step, each with its own context demonstration and batch_size / G samples from its other
    demonstrations. 1 is the paper's recipe; more prompts per step help when steps are few (a CPU)."""
    lr: float = 3e-4
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    """Linear warm-up, then cosine decay to 0 at `steps`."""
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    """Upper bound of the EMA decay (which ramps up as (1 + step) / (10 + step))."""
    seed: int = 0
    workers: int = -1
    """Data-loader worker processes per training process (0: load in the training process; -1: auto, 0 on a CPU,
    where a loader process competes with torch for the cores, and on a GPU the process's share of the cores less
    two, for the training process itself and the thread that pins its batches; at most 2 with `frames_on` device)."""
    device: str = "auto"
    """auto (cuda if available), cpu, cuda, cuda:N."""
    amp: bool = True
    """bf16 autocast where the device supports it well (CUDA); CPUs train in fp32."""
    log_every: int = 25
    save_every: int = 500
    keep_checkpoints: int = 3
    """Newest checkpoints kept on disk (0: all). One is about 4x the model's size (weights, EMA, optimizer)."""
    resume: bool = False
    """Continue the run in `out` from its last checkpoint."""
    threads: int = 0
    """torch CPU threads per process (0: auto; on a CPU, OMP_NUM_THREADS if set, else the usable cores, shared by
    the processes of a torchrun on this machine, minus one and minus the loader workers, at least 1: torch's threads
    wait for each other at every operation, so with as many threads as cores any other busy program slowed training
    2.6 to 20 times here, while one core left free costs about a third alone; see BENCHMARKS.md. -1: on a CPU, those
    cores minus the loader workers, for a run that has the machine to itself; OMP_NUM_THREADS, if set, still decides;
    beside a GPU, torch's default)."""
    frame_cache_gb: float = 4.0
    """Image observations a training process keeps once its benchmark has rendered or read them, shared evenly by
    its loader processes. Where all of the dataset's frames fit a loader's share (the CPU preset's 64x64 frames of
    2500 demonstrations take about 3 GB), whole episodes are rendered once and kept; where they do not (224x224), each
    batch renders just the frames it needs (see :class:`bpp.data.prompt_dataset.PromptBatchDataset`)."""
    channels_last: bool = True
    """On a GPU, keep the image encoders' weights and activations channels-last (NHWC), the layout the GPU's
    convolutions run fastest in; camera frames arrive in that layout already."""
    compile: CompileMode = "off"
    """Compile the training loss and its backward with ``torch.compile`` in this mode (off: run eagerly).
    ``reduce-overhead`` also records them as CUDA graphs on a GPU and replays them, so the host no longer issues
    each kernel (a GPU step of a small model is otherwise bound by launching its ~2,700 kernels); ``cudagraphs``
    records the same operators as CUDA graphs without generating new kernels. Compiling takes a minute or more at
    the start, and again for each new batch shape (see `pad_to_multiple`); on a CPU it needs a C++ compiler, and
    ``cudagraphs`` runs eagerly there."""
    frames_on: FramesOn = "loader"
    """Where camera frames are rendered. loader: by the loader (its processes), sent whole to the training process.
    device: on the training device, from references the loader sends instead (16 bytes a frame; see
    :mod:`bpp.data.frame_refs`), which leaves the loader almost nothing to do; the benchmark must offer it
    (``device_frames``) and the frames are the same (bit for bit on a CPU). State-only methods render nothing."""
    pad_to_multiple: int = -1
    """Pad the batches' variable time axes (demonstration prompts, ICRT's whole episodes) to a multiple of this many
    steps, at most the model's limit: each batch then has one of a few shapes, as a compiled step needs. Padding
    changes no result (padded steps are masked). -1: auto, none (the longest in the batch) without `compile`, and an
    eighth of the model's prompt limit with it (at most 8 prompt shapes)."""

    def __post_init__(self):
        check_fields(
            self,
            ("steps", self.steps >= 1, ">= 1"),
            ("batch_size", self.batch_size >= 1, ">= 1"),
            ("tasks_per_batch", self.tasks_per_batch >= 1, ">= 1"),
            ("lr", self.lr > 0, "> 0"),
            ("weight_decay", self.weight_decay >= 0, ">= 0"),
            ("warmup_steps", self.warmup_steps >= 0, ">= 0"),
            ("grad_clip", self.grad_clip > 0, "> 0 (a norm to clip gradients to)"),
            ("ema_decay", 0 <= self.ema_decay < 1, "in [0, 1)"),
            ("workers", self.workers >= -1, ">= -1 (-1: auto)"),
            ("log_every", self.log_every >= 1, ">= 1"),
            ("save_every", self.save_every >= 1, ">= 1"),
            ("keep_checkpoints", self.keep_checkpoints >= 0, ">= 0 (0: keep all)"),
            ("threads", self.threads >= -1, ">= -1 (0: auto, -1: every core)"),
            ("frame_cache_gb", self.frame_cache_gb >= 0, ">= 0"),
            ("pad_to_multiple", self.pad_to_multiple >= -1, ">= -1 (-1: auto, 0: no extra padding)"),
            ("compile", self.compile in COMPILE_MODES, f"one of {COMPILE_MODES}"),
            ("frames_on", self.frames_on in FRAMES_ON, f"one of {FRAMES_ON}"),
        )

    def frame_cache_share(self, workers: int) -> int:
        """Bytes of the frame cache each of `workers` loader processes keeps (0 workers: this process, all of it)."""
        return int(self.frame_cache_gb * 2**30) // max(1, workers)

    def padding(self, spec: DataSpec) -> int:
        """Steps the loader pads prompts and whole episodes to a multiple of, for a model with data spec `spec`."""
        if self.pad_to_multiple >= 0:
            return self.pad_to_multiple
        if self.compile == "off":
            return 0
        stride = spec.context_obs_stride  # a whole number of prompt chunks
        return -(-spec.max_prompt_steps // (8 * stride)) * stride
