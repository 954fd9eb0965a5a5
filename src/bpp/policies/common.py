"""Parts shared by the policies: normalisation, observation encoding, the diffusion action head, and the skeleton
of a policy that conditions that head on observations plus a task context (:class:`ContextDiffusionPolicy`)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn

from bpp.data.spec import DataSpec
from bpp.nn.lowdim import LowDimEncoder
from bpp.nn.unet1d import ConditionalUnet1D
from bpp.nn.vision import ResNetGN
from bpp.utils import check_fields


class ContextError(ValueError):
    """A task context (demonstration prompt, goal image or instruction) that a model cannot use.

    Raised by ``validate_context``; the message names the input and what was expected.
    """


class NormalizationError(ValueError):
    """Statistics and data disagree (a missing key or a different width): never silently passed through."""


class Normalizer(nn.Module):
    """Range-normalises each key to [-1, 1] from dataset min/max; stored as buffers, so it travels in checkpoints.

    Features with (almost) no range are only centred, so a constant feature maps to 0. For the keys a model
    predicts (`outputs`, e.g. the actions), :meth:`unnormalize` gives such a feature its constant back whatever the
    model produced: a dimension the data never moves (LIBERO-Gen's scripted demonstrations never roll or pitch the
    hand) is not the model's to move. Otherwise a sampler clipped to [-1, 1] could command anything in that range,
    full-speed rotations included.
    """

    def __init__(self, stats: Mapping[str, Mapping[str, list[float]]], keys: list[str], outputs: tuple[str, ...] = ()):
        super().__init__()
        self.keys = list(keys)
        for key in self.keys:
            if key not in stats:
                raise NormalizationError(f"no normalisation statistics for {key!r}; the dataset has {sorted(stats)}")
            lo = torch.tensor(stats[key]["min"], dtype=torch.float32)
            hi = torch.tensor(stats[key]["max"], dtype=torch.float32)
            span = hi - lo
            scale = torch.where(span > 1e-6, 2.0 / span.clamp_min(1e-6), torch.ones_like(span))
            offset = -(lo + hi) / 2 * scale
            self.register_buffer(f"{key}__scale", scale)
            self.register_buffer(f"{key}__offset", offset)
            if key in outputs:  # derived from the statistics, which checkpoints keep: not saved with the weights
                self.register_buffer(f"{key}__constant", span <= 1e-6, persistent=False)
                self.register_buffer(f"{key}__value", (lo + hi) / 2, persistent=False)

    def width(self, key: str) -> int:
        return getattr(self, f"{key}__scale").numel()

    def scale(self, key: str) -> torch.Tensor:
        """Normalised units per raw unit of `key`, (width,)."""
        return getattr(self, f"{key}__scale")

    def _params(self, key: str, x: torch.Tensor):
        if key not in self.keys:
            raise NormalizationError(f"no normalisation statistics for {key!r}; known keys: {self.keys}")
        scale, offset = getattr(self, f"{key}__scale"), getattr(self, f"{key}__offset")
        if x.shape[-1] != scale.numel():
            raise NormalizationError(f"{key!r} has width {x.shape[-1]}, statistics have width {scale.numel()}")
        return scale, offset

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        scale, offset = self._params(key, x)
        return x.float() * scale + offset

    def unnormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        scale, offset = self._params(key, x)
        raw = (x - offset) / scale
        constant = getattr(self, f"{key}__constant", None)
        return raw if constant is None else torch.where(constant, getattr(self, f"{key}__value"), raw)


def group_normable(channels: int) -> bool:
    """Whether the image encoder's GroupNorm (channels // 16 groups, at least 1) divides `channels`."""
    return channels >= 1 and channels % max(1, channels // 16) == 0


IMAGE_WIDTHS_RULE = (
    "channel counts >= 1, each below 16 or divisible by its GroupNorm groups (width // 16), e.g. 32, 64, 128"
)
_DOWN = "channel counts, each a multiple of 8 (the decoder's GroupNorm has 8 groups)"
BETA_SCHEDULES = ("linear", "scaled_linear", "squaredcos_cap_v2")


def transformer_rules(cfg) -> tuple[tuple[str, bool, str], ...]:
    """Range rules for the transformer fields a model config shares: dim, layers, heads, mlp_dim, dropout."""
    return (
        ("dim", cfg.dim >= 1, ">= 1"),
        ("layers", cfg.layers >= 1, ">= 1"),
        ("heads", cfg.heads >= 1 and cfg.dim % cfg.heads == 0, f"a divisor of dim ({cfg.dim})"),
        ("mlp_dim", cfg.mlp_dim >= 1, ">= 1"),
        ("dropout", 0.0 <= cfg.dropout < 1.0, "in [0, 1)"),
    )


@dataclass(frozen=True)
class ObsConfig:
    """Which observation entries a policy sees, and how they are encoded.

    The keys and the image size come from a benchmark's observation preset (:func:`with_observation`); a method's
    size preset (``debug``, ``cpu``, ``paper``) sets the encoders' sizes.
    """

    image_keys: tuple[str, ...] = ()
    """Camera keys, (H, W, 3) uint8 images (empty: state-only)."""
    lowdim_keys: tuple[str, ...] = ()
    """Low-dimensional observation keys other than proprioception (one entry each)."""
    proprio_keys: tuple[str, ...] = ()
    """Proprioception keys (one entry each); the prompt can include or drop them as a group."""
    image_size: int = 96
    image_features: int = 256
    image_widths: tuple[int, ...] = (32, 64, 128, 256)
    image_blocks: tuple[int, ...] = (1, 1, 1, 1)
    image_stem: str = "conv5"
    """resnet: ResNet's 7x7 stride-2 convolution and max-pool (the paper's ResNet-18); conv5: one 5x5 stride-2
    convolution, twice the resolution after the stem, for small images (see :class:`bpp.nn.vision.ResNetGN`)."""
    lowdim_fourier_octaves: int = 0
    """0: low-dimensional entries are their normalised values; k > 0: Fourier features over k octaves and an MLP
    to ``lowdim_features`` (a nonlinear embedding, so that attention can match nearby states; see bpp.nn.lowdim)."""
    lowdim_features: int = 64

    def __post_init__(self):
        widths, blocks = self.image_widths, self.image_blocks
        check_fields(
            self,
            ("image_size", 8 <= self.image_size <= 1024, "in [8, 1024] px"),
            ("image_features", self.image_features >= 1, ">= 1"),
            ("image_widths", len(widths) >= 1 and all(group_normable(w) for w in widths), IMAGE_WIDTHS_RULE),
            ("image_blocks", len(blocks) == len(widths) and all(b >= 1 for b in blocks), "one count >= 1 per width"),
            ("image_stem", self.image_stem in ("resnet", "conv5"), "'resnet' or 'conv5'"),
            ("lowdim_fourier_octaves", 0 <= self.lowdim_fourier_octaves <= 16, "in [0, 16]"),
            ("lowdim_features", self.lowdim_features >= 1, ">= 1"),
        )

    @property
    def entries(self) -> list[str]:
        """Observation entries in token order (one token per entry per history step): cameras, lowdim, proprio."""
        return [*self.image_keys, *self.lowdim_keys, *self.proprio_keys]


def encode_images(net: nn.Module, images: torch.Tensor) -> torch.Tensor:
    """Channels-last images (..., H, W, 3) (uint8 or [0, 1] floats) through an image encoder -> (..., F)."""
    lead = images.shape[:-3]
    flat = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)
    return net(flat).reshape(*lead, -1)


class ObsEncoder(nn.Module):
    """Raw observations -> one feature vector per entry (each camera and each low-dimensional key).

    Input: a dict of (..., dim) tensors (images (..., H, W, 3) uint8); output: a list of (..., F_e) tensors in
    :attr:`ObsConfig.entries` order. Leading dims are arbitrary (e.g. (B, To) or (B, L)).
    """

    def __init__(self, cfg: ObsConfig, normalizer: Normalizer):
        super().__init__()
        self.cfg = cfg
        self.normalizer = normalizer
        self.cameras = nn.ModuleDict(
            {
                k: ResNetGN(cfg.image_features, cfg.image_widths, cfg.image_blocks, cfg.image_stem)
                for k in cfg.image_keys
            }
        )
        lowdim = (*cfg.lowdim_keys, *cfg.proprio_keys)
        self.lowdim = nn.ModuleDict(
            {
                k: LowDimEncoder(normalizer.width(k), cfg.lowdim_features, cfg.lowdim_fourier_octaves)
                for k in (lowdim if cfg.lowdim_fourier_octaves > 0 else ())
            }
        )
        self.dims = [cfg.image_features] * len(cfg.image_keys)
        self.dims += [cfg.lowdim_features if k in self.lowdim else normalizer.width(k) for k in lowdim]

    def forward(self, obs: Mapping[str, torch.Tensor]) -> list[torch.Tensor]:
        out = []
        for key, net in self.cameras.items():
            out.append(encode_images(net, obs[key]))
        for key in (*self.cfg.lowdim_keys, *self.cfg.proprio_keys):
            x = self.normalizer.normalize(key, obs[key])
            out.append(self.lowdim[key](x) if key in self.lowdim else x)
        return out


@dataclass(frozen=True)
class DiffusionConfig:
    """The action decoder: a FiLM 1D U-Net trained with DDPM and sampled with DDIM (diffusers schedulers)."""

    down_dims: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 5
    step_embed_dim: int = 64
    num_train_steps: int = 100
    """K: diffusion steps at training."""
    num_inference_steps: int = 16
    """Denoising steps at inference (DDIM)."""
    beta_schedule: str = "squaredcos_cap_v2"
    sampler: str = "ddim"
    """ddim or ddpm."""

    def __post_init__(self):
        check_fields(
            self,
            ("down_dims", len(self.down_dims) >= 1 and all(d >= 8 and d % 8 == 0 for d in self.down_dims), _DOWN),
            ("kernel_size", self.kernel_size >= 1 and self.kernel_size % 2 == 1, "odd and >= 1"),
            ("step_embed_dim", self.step_embed_dim >= 2 and self.step_embed_dim % 2 == 0, "even and >= 2"),
            ("num_train_steps", 1 <= self.num_train_steps <= 10_000, "in [1, 10000]"),
            ("num_inference_steps", 1 <= self.num_inference_steps <= self.num_train_steps, "in [1, num_train_steps]"),
            ("beta_schedule", self.beta_schedule in BETA_SCHEDULES, f"one of {BETA_SCHEDULES}"),
            ("sampler", self.sampler in ("ddim", "ddpm"), "'ddim' or 'ddpm'"),
        )

    def check_horizon(self, horizon: int) -> None:
        """The U-Net halves the time axis between levels: refuse a horizon it cannot halve that often."""
        factor = 2 ** (len(self.down_dims) - 1)
        if horizon % factor:
            raise ValueError(
                f"horizons.horizon {horizon} must be a multiple of {factor} for a decoder with "
                f"{len(self.down_dims)} levels (diffusion.down_dims {self.down_dims})"
            )


class DiffusionHead(nn.Module):
    """Epsilon-prediction diffusion over normalised action chunks (B, T, A), conditioned on a vector (B, C)."""

    def __init__(self, cfg: DiffusionConfig, action_dim: int, cond_dim: int):
        super().__init__()
        from diffusers import DDIMScheduler, DDPMScheduler

        self.cfg = cfg
        self.net = ConditionalUnet1D(action_dim, cond_dim, cfg.down_dims, cfg.kernel_size, cfg.step_embed_dim)
        common = dict(
            num_train_timesteps=cfg.num_train_steps,
            beta_schedule=cfg.beta_schedule,
            clip_sample=True,
            prediction_type="epsilon",
        )
        self.train_scheduler = DDPMScheduler(**common)
        # ᾱ_t for noising training samples, as a buffer: it moves with the model, so a compiled loss on a GPU reads
        # no CPU tensor (one would keep it from being replayed as a CUDA graph). Not saved: the schedule defines it.
        self.register_buffer("alphas_cumprod", self.train_scheduler.alphas_cumprod.clone(), persistent=False)
        self.sample_scheduler = (DDIMScheduler if cfg.sampler == "ddim" else DDPMScheduler)(**common)
        self.cuda_graphs = False
        """Replay DDIM sampling on a GPU from a CUDA graph (see :meth:`sample`); the agent turns it on for CUDA."""
        self._graphs: dict = {}

    def draw_noise(
        self, shape: tuple[int, ...], device: torch.device, generator: torch.Generator | None = None
    ) -> dict[str, torch.Tensor]:
        """The random draws of one loss evaluation for action chunks of `shape` (B, T, A): ``{"noise": (B, T, A),
        "timesteps": (B,)}``."""
        noise = torch.randn(shape, device=device, generator=generator)
        steps = torch.randint(0, self.cfg.num_train_steps, (shape[0],), device=device, generator=generator)
        return {"noise": noise, "timesteps": steps}

    def loss(
        self,
        actions: torch.Tensor,
        cond: torch.Tensor,
        generator: torch.Generator | None = None,
        noise: Mapping[str, torch.Tensor] | None = None,
    ):
        """Mean squared noise-prediction error for normalised actions (B, T, A), with the draws `noise` (see
        :meth:`draw_noise`; made here from `generator` if None)."""
        if noise is None:
            noise = self.draw_noise(actions.shape, actions.device, generator)
        eps, steps = noise["noise"], noise["timesteps"]
        alpha = self.alphas_cumprod.to(actions.dtype)[steps][:, None, None]  # the DDPM scheduler's add_noise
        noisy = alpha**0.5 * actions + (1 - alpha) ** 0.5 * eps
        return nn.functional.mse_loss(self.net(noisy, steps, cond), eps)

    def set_inference_steps(self, steps: int) -> None:
        """Denoise in `steps` DDIM/DDPM steps at inference from now on (training is unaffected)."""
        if not 1 <= steps <= self.cfg.num_train_steps:
            raise ValueError(
                f"inference steps must be in [1, {self.cfg.num_train_steps}] (the training steps), got {steps}"
            )
        self.cfg = replace(self.cfg, num_inference_steps=steps)

    @torch.no_grad()
    def sample(
        self,
        cond: torch.Tensor,
        shape: tuple[int, int],
        noise: torch.Tensor | None = None,
        generator: torch.Generator | list[torch.Generator] | None = None,
    ):
        """Denoise from `noise` (B, T, A) (drawn if None) to normalised actions (B, T, A).

        `generator`: one for the batch, or a list of B, one per sample, so that a sample's result (including the
        DDPM sampler's per-step noise) does not depend on which other samples share its batch. With
        :attr:`cuda_graphs` set, a DDIM loop on a GPU is recorded once per shape as a CUDA graph and replayed."""
        from diffusers.utils.torch_utils import randn_tensor

        if noise is None:
            noise = randn_tensor((cond.shape[0], *shape), generator=generator, device=cond.device)
        # The time steps stay on the CPU and the loop reads them as Python ints: nothing waits for the GPU between
        # denoising steps (a CUDA time step made the scheduler read it back three times per step).
        self.sample_scheduler.set_timesteps(self.cfg.num_inference_steps)
        if self.cuda_graphs and cond.is_cuda and self.cfg.sampler == "ddim":
            try:
                return self._graphed_denoise(cond, noise)
            except RuntimeError as error:  # a GPU or driver that cannot record this loop: sample as before
                warnings.warn(f"CUDA-graph sampling failed, sampling without it from now on: {error}", stacklevel=2)
                self.cuda_graphs = False
                self._graphs.clear()
        return self._denoise(cond, noise, generator)

    def _denoise(self, cond: torch.Tensor, x: torch.Tensor, generator=None) -> torch.Tensor:
        for t in self.sample_scheduler.timesteps.tolist():
            eps = self.net(x, torch.full((x.shape[0],), t, dtype=torch.long, device=x.device), cond)
            x = self.sample_scheduler.step(eps, t, x, generator=generator).prev_sample
        return x

    def _graphed_denoise(self, cond: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The DDIM loop as one CUDA graph: launching a small network's kernels one by one costs more than running
        them at batch 1. DDIM draws no noise, and the schedule's scalars are fixed per step count, so the whole loop
        replays from new `cond` and `noise` copied into the recorded inputs."""
        weights = next(self.net.parameters()).data_ptr()  # a moved model needs a new graph
        key = (tuple(noise.shape), tuple(cond.shape), cond.dtype, self.cfg.num_inference_steps, weights)
        if key not in self._graphs:
            self._graphs.clear()
            static_cond, static_noise = cond.clone(), noise.clone()
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):  # warm-up outside the graph (cuDNN's choices, the allocator)
                self._denoise(static_cond, static_noise)
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                out = self._denoise(static_cond, static_noise)
            self._graphs[key] = (graph, static_cond, static_noise, out)
        graph, static_cond, static_noise, out = self._graphs[key]
        static_cond.copy_(cond)
        static_noise.copy_(noise)
        graph.replay()
        return out.clone()


@dataclass(frozen=True)
class Horizons:
    """To (n_obs_steps), T (horizon) and Ta (n_action_steps); the executed actions start at index To - 1."""

    n_obs_steps: int = 2
    horizon: int = 16
    n_action_steps: int = 12

    def __post_init__(self):
        check_fields(
            self,
            ("n_obs_steps", self.n_obs_steps >= 1, ">= 1"),
            ("horizon", self.n_obs_steps <= self.horizon <= 1024, "in [n_obs_steps, 1024]"),
        )
        if not 1 <= self.n_action_steps <= self.horizon - self.n_obs_steps + 1:
            raise ValueError(
                f"need 1 <= n_action_steps <= horizon - n_obs_steps + 1, got Ta={self.n_action_steps}, "
                f"T={self.horizon}, To={self.n_obs_steps}"
            )


# Size-preset parts that several methods share (each method's config.py names its own size presets; the keys come
# from a benchmark's observation preset, see with_observation).
DEBUG_DIFFUSION = DiffusionConfig(down_dims=(32, 64), step_embed_dim=16, num_train_steps=20, num_inference_steps=4)
"""The tiny action decoder of the ``debug`` presets."""
DEBUG_OBS = ObsConfig(image_features=16, image_widths=(8, 16), image_blocks=(1, 1))
"""The ``debug`` presets' encoders: normalised state, a tiny image encoder."""
CPU_OBS = ObsConfig(lowdim_fourier_octaves=6, image_features=128, image_widths=(16, 32, 64, 128))
"""The ``cpu`` presets' encoders: Fourier-feature embeddings of every low-dimensional entry (see bpp.nn.lowdim for
why), a small ResNet-GN for cameras (64x64 images on a CPU)."""
PAPER_OBS = ObsConfig(
    image_features=512, image_widths=(64, 128, 256, 512), image_blocks=(2, 2, 2, 2), image_stem="resnet"
)
"""The paper's encoders: ResNet-18 (GroupNorm, ResNet's stem) for cameras."""
PAPER_DIFFUSION = DiffusionConfig(down_dims=(256, 512, 1024), step_embed_dim=128)
"""The paper's action decoder: U-Net [256, 512, 1024], kernel 5, step embedding 128."""


def with_observation(cfg, preset):
    """A method config (any with ``obs`` and ``action_key``) that observes and acts as a benchmark's observation
    preset says (:class:`bpp.data.spec.ObservationPreset`): its keys, image size and action key. The encoders keep
    the size preset's widths. A config class may define ``observation_overrides(obs, preset) -> dict`` for fields
    that follow the observations (e.g. Goal-Image's goal camera, and its size when it shares the camera encoder)."""
    obs = replace(
        cfg.obs,
        image_keys=tuple(preset.image_keys),
        lowdim_keys=tuple(preset.lowdim_keys),
        proprio_keys=tuple(preset.proprio_keys),
        image_size=preset.image_size,
    )
    fields = {"obs": obs, "action_key": preset.action_key}
    hook = getattr(cfg, "observation_overrides", None)
    if hook is not None:
        fields.update(hook(obs, preset))
    return replace(cfg, **fields)


def keep_eager(model: nn.Module) -> nn.Module:
    """`model` with the methods its modules name in ``never_compiled`` left to Python by ``torch.compile`` (each
    call a break between two graphs); call it before compiling. Not done when a model is built, because it imports
    ``torch._dynamo``, which takes seconds, in every process that loads a policy."""
    for module in model.modules():
        for name in getattr(module, "never_compiled", ()):
            method = getattr(module, name)
            if not getattr(method, "_kept_eager", False):
                method = torch.compiler.disable(method)
                method._kept_eager = True
                setattr(module, name, method)
    return model


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


class PolicyModel(nn.Module):
    """The parts of the model contract (:mod:`bpp.policies.registry`) that every method shares: the normaliser,
    the observation encoder, ``forward`` = ``compute_loss``, the keys read and the training batches wanted.

    ``cfg`` needs ``obs`` (:class:`ObsConfig`), ``horizons``, ``action_key`` and ``action_relative_to``. A method
    sets ``method`` and ``context_kind`` and may add :class:`DataSpec` fields in :meth:`context_spec`.
    """

    method: str
    context_kind: str

    def __init__(self, cfg, stats: Mapping[str, Mapping[str, list[float]]]):
        super().__init__()
        self.cfg = cfg
        obs = cfg.obs
        if not obs.entries:
            raise ValueError(
                f"{type(self).__name__}: the config observes nothing; combine the size preset with a benchmark's "
                "observation preset (bpp.policies.registry.Method.config, or bpp train --obs NAME)"
            )
        keys = [*obs.lowdim_keys, *obs.proprio_keys, cfg.action_key]
        self.normalizer = Normalizer(stats, keys, outputs=(cfg.action_key,))
        self.action_dim = self.normalizer.width(cfg.action_key)
        self.obs_encoder = ObsEncoder(obs, self.normalizer)
        origin = cfg.action_relative_to
        if origin:
            if origin not in (*obs.lowdim_keys, *obs.proprio_keys):
                raise ValueError(f"action_relative_to {origin!r} must be an observed low-dimensional key")
            if self.normalizer.width(origin) > self.action_dim:
                raise ValueError(f"action_relative_to {origin!r} is wider than the actions ({self.action_dim})")
        self.relative_dims = self.normalizer.width(origin) if origin else 0

    # ----------------------------------------------------------------- actions
    def _relative_scale(self) -> torch.Tensor:
        # Offsets are scaled by the absolute actions' range: an offset as large as that whole range maps to 1, so
        # a T-step chunk at the demonstrations' speeds stays inside the sampler's [-1, 1] clip.
        return self.normalizer.scale(self.cfg.action_key)[: self.relative_dims] / 2

    def normalize_actions(self, actions: torch.Tensor, origin: torch.Tensor | None) -> torch.Tensor:
        """Raw actions (..., T, A) -> the model's normalised action space.

        Absolute by default. With ``cfg.action_relative_to`` set, the first P dims become offsets from `origin`
        (..., 1 or T, P), the raw value of that observation key (e.g. the cursor at the current step), so a chunk
        that continues from where the robot is sits near 0 whatever the position.
        """
        x = self.normalizer.normalize(self.cfg.action_key, actions)
        if not self.relative_dims:
            return x
        P = self.relative_dims
        return torch.cat([(actions[..., :P] - origin) * self._relative_scale(), x[..., P:]], dim=-1)

    def unnormalize_actions(self, x: torch.Tensor, origin: torch.Tensor | None) -> torch.Tensor:
        """The inverse of :meth:`normalize_actions`."""
        actions = self.normalizer.unnormalize(self.cfg.action_key, x)
        if not self.relative_dims:
            return actions
        P = self.relative_dims
        return torch.cat([x[..., :P] / self._relative_scale() + origin, actions[..., P:]], dim=-1)

    @staticmethod
    def chunk_obs(demo: Mapping, chunk_len: int) -> dict[str, torch.Tensor]:
        """A demonstration context's observations at its chunks' first steps, ``{key: (B, n, ...)}``: taken here
        from every step's, or already so by the data loader (a context with ``obs_stride``; see
        :attr:`bpp.data.spec.DataSpec.context_obs_stride`, which a model sets to its chunk length)."""
        if "obs_stride" in demo:
            return dict(demo["obs"])
        return {k: v[:, ::chunk_len] for k, v in demo["obs"].items()}

    def chunk_origins(
        self, obs: Mapping[str, torch.Tensor], chunk_len: int, steps: int | None = None
    ) -> torch.Tensor | None:
        """Per-step origins (B, L, P) for demonstrations ``{key: (B, L, ...)}`` cut into chunks of `chunk_len`
        steps: each step's actions are relative to the observation at its chunk's first step. With `steps` (L),
        `obs` holds the chunks' first steps only, ``{key: (B, n, ...)}`` (:meth:`chunk_obs`)."""
        if not self.relative_dims:
            return None
        value = obs[self.cfg.action_relative_to].float()
        if steps is None:
            value, steps = value[:, ::chunk_len], value.shape[1]
        return value.repeat_interleave(chunk_len, dim=1)[:, :steps]

    def action_origin(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
        """Where relative actions start for observations ``{key: (B, To, ...)}``: (B, 1, P) at the current step."""
        return obs[self.cfg.action_relative_to][:, -1:].float() if self.relative_dims else None

    def forward(
        self, batch: Mapping, generator: torch.Generator | None = None, noise: Mapping | None = None
    ) -> torch.Tensor:
        """The training loss (``forward`` so that DDP's gradient hooks see it)."""
        return self.compute_loss(batch, generator, noise)

    def compute_loss(
        self, batch: Mapping, generator: torch.Generator | None = None, noise: Mapping | None = None
    ) -> torch.Tensor:
        """The training loss of `batch`: its random draws are `noise` (:meth:`draw_noise`), or made from
        `generator` if None."""
        raise NotImplementedError

    def draw_noise(self, batch: Mapping, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The random tensors one loss evaluation of `batch` uses, drawn from `generator` (none here).

        The training loop draws them before the loss rather than inside it: the loss is then a pure function of its
        inputs, which ``torch.compile`` captures as one graph (a generator inside it splits the graph) and a GPU can
        replay. Dropout is the exception: it draws from torch's global generator, which the loop seeds per step."""
        return {}

    def set_inference_steps(self, steps: int) -> None:
        """Denoise in `steps` steps per inference from now on; models without a diffusion decoder refuse."""
        raise ValueError(f"{type(self).__name__} has no diffusion decoder: it takes no inference steps")

    def check_action_steps(self, n_action_steps: int) -> None:
        """Refuse (ValueError) an agent that would execute `n_action_steps` actions of each predicted chunk."""
        h = self.cfg.horizons
        if not 1 <= n_action_steps <= h.horizon - h.n_obs_steps + 1:
            raise ValueError(
                f"n_action_steps must be in [1, {h.horizon - h.n_obs_steps + 1}] (horizon T={h.horizon}, "
                f"To={h.n_obs_steps}), got {n_action_steps}"
            )

    def obs_keys(self) -> list[str]:
        """Per-step observation keys the policy reads (and a demonstration prompt must provide)."""
        return self.cfg.obs.entries

    def data_spec(self) -> DataSpec:
        """What training batches must contain for this model."""
        obs, h = self.cfg.obs, self.cfg.horizons
        return DataSpec(
            lowdim_keys=(*obs.lowdim_keys, *obs.proprio_keys),
            image_keys=obs.image_keys,
            image_size=obs.image_size,
            action_key=self.cfg.action_key,
            n_obs_steps=h.n_obs_steps,
            horizon=h.horizon,
            context=self.context_kind,
            **self.context_spec(),
        )

    def context_spec(self) -> dict:
        """The method's own :class:`DataSpec` fields (e.g. the goal image's size, or whole-episode samples)."""
        return {}


class ContextDiffusionPolicy(PolicyModel):
    """What every method with the diffusion action decoder shares: the loss, sampling and the conditioning.

    A method adds how it encodes its task context once (``encode_context``), checks a raw one
    (``validate_context``), and how context and observations become the decoder's conditioning vector
    (:meth:`condition`). The default conditioning is the diffusion-policy one: a context vector (B or 1, C)
    concatenated with the flattened observation features of the To history steps. A subclass builds its own
    modules in ``__init__``, then calls :meth:`build_head` with the width C of its context features.

    ``cfg`` also needs ``diffusion``.
    """

    def set_inference_steps(self, steps: int) -> None:
        self.head.set_inference_steps(steps)

    def build_head(self, context_dim: int) -> None:
        """The action decoder, conditioned on `context_dim` context features + the observation history."""
        obs_dim = self.cfg.horizons.n_obs_steps * sum(self.obs_encoder.dims)
        self.head = DiffusionHead(self.cfg.diffusion, self.action_dim, context_dim + obs_dim)

    # ------------------------------------------------------------- conditioning
    @staticmethod
    def flatten_obs(features: list[torch.Tensor]) -> torch.Tensor:
        """Per-entry observation features [(B, To, F_e)] -> (B, To * sum F_e), the decoder's observation part."""
        return torch.cat(features, dim=-1).flatten(1)

    def condition(
        self, obs: Mapping[str, torch.Tensor], ctx: torch.Tensor, return_attention: bool = False
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Observations ``{key: (B, To, ...)}`` + context features (B or 1, C) -> conditioning (B, C + To * F).

        Returns the conditioning and attention maps (none here; methods with attention override this).
        """
        features = self.flatten_obs(self.obs_encoder(obs))
        batch = features.shape[0]
        ctx = ctx.expand(batch, -1) if ctx.shape[0] == 1 else ctx
        assert ctx.shape[0] == batch, f"context batch {ctx.shape[0]} vs observation batch {batch}"
        return torch.cat([ctx, features], dim=-1), []

    def compute_loss(
        self, batch: Mapping, generator: torch.Generator | None = None, noise: Mapping | None = None
    ) -> torch.Tensor:
        """Noise-prediction loss of a batch ``{"obs": {k: (B, To, ...)}, "action": (B, T, A), "context": ...,
        "context_index": (B,)}``: G contexts, each encoded once, sample i conditioned on context_index[i]."""
        ctx = self.encode_context(batch["context"])
        if "context_index" in batch:
            ctx = self.select_context(ctx, batch["context_index"])
        cond, _ = self.condition(batch["obs"], ctx)
        actions = self.normalize_actions(batch["action"], self.action_origin(batch["obs"]))
        return self.head.loss(actions, cond, generator, noise)

    def draw_noise(self, batch: Mapping, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The diffusion noise and time steps of `batch`'s samples (:meth:`DiffusionHead.draw_noise`)."""
        return self.head.draw_noise(tuple(batch["action"].shape), batch["action"].device, generator)

    def encode_context(self, context: Mapping):
        """A batched, validated context (tensors) -> whatever :meth:`condition` takes; once per rollout."""
        raise NotImplementedError

    @staticmethod
    def select_context(ctx: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Encoded contexts (G, ...) -> one per sample (B, ...), sample i taking context ``index[i]``."""
        return ctx[index]

    @torch.no_grad()
    def predict_action(
        self,
        obs: Mapping[str, torch.Tensor],
        ctx,
        noise: torch.Tensor | None = None,
        generator: torch.Generator | list[torch.Generator] | None = None,
        return_attention: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Action chunk (B, T, A) in raw units from `noise` (B, T, A) (drawn from `generator` if None; a list of B
        generators draws each sample's noise, and a DDPM sampler's per-step noise, from its own).

        With `return_attention`, methods that attend to their context also return ``"attention"``.
        """
        cond, attentions = self.condition(obs, ctx, return_attention)
        shape = (self.cfg.horizons.horizon, self.action_dim)
        sample = self.head.sample(cond, shape, noise, generator)
        actions = self.unnormalize_actions(sample, self.action_origin(obs))
        out = {"action": actions}
        if return_attention and attentions:
            out["attention"] = self.context_attention(attentions, ctx)
        return out

    def context_attention(self, attentions: list[torch.Tensor], ctx) -> torch.Tensor:
        raise NotImplementedError


class PromptError(ContextError):
    """A demonstration prompt that a model cannot use; the message says what was expected."""


def validate_demo_context(
    prompt: Mapping,
    obs_cfg: ObsConfig,
    normalizer: Normalizer,
    action_key: str,
    chunk_len: int,
    max_steps: int,
    limit_note: str = "",
) -> dict:
    """Check a raw demonstration prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` and batch it.

    Every observation entry of `obs_cfg` must be present with L steps (images (L, H, W, 3) at the model's size,
    low-dimensional keys at their statistics' width, finite), actions (L, A) finite, and L between one chunk
    (`chunk_len`) and `max_steps` (`limit_note` may say why that limit). Returns the prompt with batch dimension 1
    and ``valid`` (1, L) all True; raises :class:`PromptError` naming the input and what was expected.
    """
    if not isinstance(prompt, Mapping) or "obs" not in prompt or "action" not in prompt:
        raise PromptError("a prompt must be a dict with 'obs' (a dict of per-step arrays) and 'action'")
    action_dim = normalizer.width(action_key)
    actions = np.asarray(prompt["action"], dtype=np.float32)
    if actions.ndim != 2 or actions.shape[1] != action_dim:
        raise PromptError(f"prompt actions must have shape (steps, {action_dim}) as in training, got {actions.shape}")
    steps = len(actions)
    if steps < chunk_len:
        raise PromptError(f"prompt has {steps} steps; at least one chunk of {chunk_len} steps is needed")
    if steps > max_steps:
        raise PromptError(f"prompt has {steps} steps; this model accepts at most {max_steps}{limit_note}")
    if not np.all(np.isfinite(actions)):
        raise PromptError("prompt actions contain NaN or infinite values")
    obs = {}
    for key in obs_cfg.entries:
        if key not in prompt["obs"]:
            raise PromptError(f"prompt obs lacks {key!r}; expected keys {obs_cfg.entries}")
        value = np.asarray(prompt["obs"][key])
        if len(value) != steps:
            raise PromptError(f"prompt obs {key!r} has {len(value)} steps, actions have {steps}")
        if key in obs_cfg.image_keys:
            size = obs_cfg.image_size
            if value.shape[1:] != (size, size, 3):
                raise PromptError(f"prompt images {key!r} must be (steps, {size}, {size}, 3), got {value.shape}")
        else:
            width = normalizer.width(key)
            if value.ndim != 2 or value.shape[1] != width:
                raise PromptError(f"prompt obs {key!r} must be (steps, {width}), got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise PromptError(f"prompt obs {key!r} contains NaN or infinite values")
        obs[key] = value[None]
    return {"obs": obs, "action": actions[None], "valid": np.ones((1, steps), dtype=bool)}
