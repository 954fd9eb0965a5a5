"""Parts shared by the policies: normalisation, observation encoding and the diffusion action head."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from bpp.nn.unet1d import ConditionalUnet1D
from bpp.nn.vision import ResNetGN


class NormalizationError(ValueError):
    """Statistics and data disagree (a missing key or a different width): never silently passed through."""


class Normalizer(nn.Module):
    """Range-normalises each key to [-1, 1] from dataset min/max; stored as buffers, so it travels in checkpoints.

    Features with (almost) no range are only centred, so a constant feature maps to 0.
    """

    def __init__(self, stats: Mapping[str, Mapping[str, list[float]]], keys: list[str]):
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

    def width(self, key: str) -> int:
        return getattr(self, f"{key}__scale").numel()

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
        return (x - offset) / scale


@dataclass(frozen=True)
class ObsConfig:
    """Which observation entries a policy sees, and how images are encoded."""

    image_keys: tuple[str, ...] = ()
    """Camera keys, (H, W, 3) uint8 images (empty: state-only)."""
    lowdim_keys: tuple[str, ...] = ("board_pose", "cursor_on_board")
    """Low-dimensional observation keys other than proprioception (one entry each)."""
    proprio_keys: tuple[str, ...] = ("agent_pos", "pen_down")
    """Proprioception keys (one entry each); the prompt can include or drop them as a group."""
    image_size: int = 96
    image_features: int = 256
    image_widths: tuple[int, ...] = (32, 64, 128, 256)
    image_blocks: tuple[int, ...] = (1, 1, 1, 1)

    @property
    def entries(self) -> list[str]:
        """Observation entries in token order (one token per entry per history step): cameras, lowdim, proprio."""
        return [*self.image_keys, *self.lowdim_keys, *self.proprio_keys]


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
            {k: ResNetGN(cfg.image_features, cfg.image_widths, cfg.image_blocks) for k in cfg.image_keys}
        )
        self.dims = [cfg.image_features] * len(cfg.image_keys)
        self.dims += [normalizer.width(k) for k in (*cfg.lowdim_keys, *cfg.proprio_keys)]

    def forward(self, obs: Mapping[str, torch.Tensor]) -> list[torch.Tensor]:
        out = []
        for key, net in self.cameras.items():
            images = obs[key]
            lead = images.shape[:-3]
            flat = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)
            out.append(net(flat).reshape(*lead, -1))
        for key in (*self.cfg.lowdim_keys, *self.cfg.proprio_keys):
            out.append(self.normalizer.normalize(key, obs[key]))
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
        if self.sampler not in ("ddim", "ddpm"):
            raise ValueError(f"sampler must be 'ddim' or 'ddpm', got {self.sampler!r}")


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
        self.sample_scheduler = (DDIMScheduler if cfg.sampler == "ddim" else DDPMScheduler)(**common)

    def loss(self, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None):
        """Mean squared noise-prediction error for normalised actions (B, T, A)."""
        noise = torch.randn(actions.shape, device=actions.device, generator=generator)
        steps = torch.randint(
            0, self.cfg.num_train_steps, (actions.shape[0],), device=actions.device, generator=generator
        )
        noisy = self.train_scheduler.add_noise(actions, noise, steps)
        return nn.functional.mse_loss(self.net(noisy, steps, cond), noise)

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, shape: tuple[int, int], noise: torch.Tensor | None = None, generator=None):
        """Denoise from `noise` (B, T, A) (drawn if None) to normalised actions (B, T, A)."""
        if noise is None:
            noise = torch.randn((cond.shape[0], *shape), device=cond.device, generator=generator)
        scheduler = self.sample_scheduler
        scheduler.set_timesteps(self.cfg.num_inference_steps, device=cond.device)
        x = noise
        for t in scheduler.timesteps:
            eps = self.net(x, t.to(cond.device).expand(x.shape[0]), cond)
            x = scheduler.step(eps, t, x, generator=generator).prev_sample
        return x


@dataclass(frozen=True)
class Horizons:
    """To (n_obs_steps), T (horizon) and Ta (n_action_steps); the executed actions start at index To - 1."""

    n_obs_steps: int = 2
    horizon: int = 16
    n_action_steps: int = 12

    def __post_init__(self):
        if not 1 <= self.n_action_steps <= self.horizon - self.n_obs_steps + 1:
            raise ValueError(
                f"need 1 <= n_action_steps <= horizon - n_obs_steps + 1, got Ta={self.n_action_steps}, "
                f"T={self.horizon}, To={self.n_obs_steps}"
            )


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def collate_contexts(items: list) -> object:
    """Stack validated task contexts (each with batch dimension 1) into one batch.

    Arrays are concatenated along the batch axis; arrays whose time axis (axis 1) differs are zero-padded to
    the longest first, so a demonstration's ``valid`` mask pads with False. Lists (e.g. instructions) are joined.
    """
    first = items[0]
    if isinstance(first, Mapping):
        return {k: collate_contexts([item[k] for item in items]) for k in first}
    if isinstance(first, list):
        return [x for item in items for x in item]
    arrays = [np.asarray(a) for a in items]
    if arrays[0].ndim >= 2:
        longest = max(a.shape[1] for a in arrays)
        arrays = [np.pad(a, [(0, 0), (0, longest - a.shape[1])] + [(0, 0)] * (a.ndim - 2)) for a in arrays]
    return np.concatenate(arrays, axis=0)
