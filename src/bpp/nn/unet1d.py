"""The 1D-convolution U-Net with FiLM conditioning used as the action decoder (after Diffusion Policy).

Actions (B, T, A) are treated as an A-channel signal over T steps. Every residual block is modulated by a
feature-wise affine transform (scale and shift per channel, "FiLM") predicted from the conditioning vector:
the diffusion-step embedding concatenated with the task/observation features.
"""

from __future__ import annotations

import math

import torch
from einops import rearrange
from torch import nn

from bpp.nn.norm import GroupNorm


class SinusoidalEmbedding(nn.Module):
    """(B,) diffusion steps -> (B, dim) sinusoidal features."""

    def __init__(self, dim: int):
        super().__init__()
        assert dim % 2 == 0, "embedding dim must be even"
        self.dim = dim

    def forward(self, steps: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=steps.device) / (half - 1))
        angles = steps.float()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class ConvNormAct(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int, groups: int):
        super().__init__(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), GroupNorm(groups, c_out), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks; the first one's output is scaled and shifted per channel from the conditioning vector."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel: int, groups: int):
        super().__init__()
        self.conv1 = ConvNormAct(c_in, c_out, kernel, groups)
        self.conv2 = ConvNormAct(c_out, c_out, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x: (B, C_in, T), cond: (B, cond_dim) -> (B, C_out, T)."""
        scale, shift = rearrange(self.film(cond), "b (two c) -> two b c 1", two=2)
        h = self.conv1(x) * scale + shift
        return self.conv2(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """Noise-prediction network: (noisy actions (B, T, A), steps (B,), cond (B, C)) -> (B, T, A).

    Args:
        action_dim: A.
        cond_dim: size of the global conditioning vector (observation + task features).
        down_dims: channels at each resolution; T is halved between levels (T must be divisible by
            2 ** (len(down_dims) - 1)).
        kernel_size: temporal kernel of every convolution.
        step_embed_dim: size of the diffusion-step embedding.
        groups: GroupNorm groups.
    """

    def __init__(
        self,
        action_dim: int,
        cond_dim: int,
        down_dims: tuple[int, ...] = (256, 512, 1024),
        kernel_size: int = 5,
        step_embed_dim: int = 128,
        groups: int = 8,
    ):
        super().__init__()
        self.down_factor = 2 ** (len(down_dims) - 1)
        self.step_embed = nn.Sequential(
            SinusoidalEmbedding(step_embed_dim),
            nn.Linear(step_embed_dim, 4 * step_embed_dim),
            nn.Mish(),
            nn.Linear(4 * step_embed_dim, step_embed_dim),
        )
        film_dim = step_embed_dim + cond_dim
        channels = [action_dim, *down_dims]
        self.down = nn.ModuleList()
        for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:], strict=True)):
            last = i == len(down_dims) - 1
            self.down.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(c_in, c_out, film_dim, kernel_size, groups),
                        FiLMResBlock(c_out, c_out, film_dim, kernel_size, groups),
                        nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1),
                    ]
                )
            )
        mid = down_dims[-1]
        self.mid = nn.ModuleList(
            [
                FiLMResBlock(mid, mid, film_dim, kernel_size, groups),
                FiLMResBlock(mid, mid, film_dim, kernel_size, groups),
            ]
        )
        self.up = nn.ModuleList()
        for c_out, c_skip in zip(reversed(down_dims[:-1]), reversed(down_dims[1:]), strict=True):
            self.up.append(
                nn.ModuleList(
                    [
                        FiLMResBlock(2 * c_skip, c_out, film_dim, kernel_size, groups),
                        FiLMResBlock(c_out, c_out, film_dim, kernel_size, groups),
                        nn.ConvTranspose1d(c_out, c_out, 4, stride=2, padding=1),
                    ]
                )
            )
        self.head = nn.Sequential(
            ConvNormAct(down_dims[0], down_dims[0], kernel_size, groups), nn.Conv1d(down_dims[0], action_dim, 1)
        )

    def forward(self, actions: torch.Tensor, steps: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        if actions.shape[1] % self.down_factor:
            raise ValueError(f"horizon {actions.shape[1]} must be divisible by {self.down_factor}")
        film = torch.cat([self.step_embed(steps.expand(actions.shape[0])), cond], dim=-1)
        x = rearrange(actions, "b t a -> b a t")
        skips = []
        for block1, block2, downsample in self.down:
            x = block2(block1(x, film), film)
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, film)
        for block1, block2, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(block2(block1(x, film), film))
        return rearrange(self.head(x), "b a t -> b t a")
