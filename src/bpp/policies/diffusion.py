"""The diffusion action head: a FiLM 1D U-Net over action chunks, trained with DDPM, sampled with DDIM (or
DDPM), optionally replayed from a CUDA graph."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import replace

import torch
from torch import nn

from bpp.errors import UserError
from bpp.nn.unet1d import ConditionalUnet1D
from bpp.policies.config import DiffusionConfig


class DiffusionHead(nn.Module):
    """Diffusion over normalised action chunks (B, T, A), conditioned on a vector (B, C); the network predicts the
    noise, the clean chunk or v (``cfg.prediction_type``)."""

    def __init__(self, cfg: DiffusionConfig, action_dim: int, cond_dim: int):
        super().__init__()
        # diffusers: seconds to import, for the diffusion decoder only
        from diffusers import DDIMScheduler, DDPMScheduler

        self.cfg = cfg
        self.net = ConditionalUnet1D(action_dim, cond_dim, cfg.down_dims, cfg.kernel_size, cfg.step_embed_dim)
        common = dict(
            num_train_timesteps=cfg.num_train_steps,
            beta_schedule=cfg.beta_schedule,
            clip_sample=True,
            prediction_type=cfg.prediction_type,
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
        """Mean squared error of the network's prediction (the noise, the clean chunk or v, as
        ``cfg.prediction_type`` says) for normalised actions (B, T, A), with the draws `noise` (see :meth:`draw_noise`;
        made here from `generator` if None)."""
        if noise is None:
            noise = self.draw_noise(actions.shape, actions.device, generator)
        eps, steps = noise["noise"], noise["timesteps"]
        alpha = self.alphas_cumprod.to(actions.dtype)[steps][:, None, None]  # the DDPM scheduler's add_noise
        noisy = alpha**0.5 * actions + (1 - alpha) ** 0.5 * eps
        if self.cfg.prediction_type == "epsilon":
            target = eps
        elif self.cfg.prediction_type == "sample":
            target = actions
        else:  # v_prediction
            target = alpha**0.5 * eps - (1 - alpha) ** 0.5 * actions
        return nn.functional.mse_loss(self.net(noisy, steps, cond), target)

    def set_inference_steps(self, steps: int) -> None:
        """Denoise in `steps` DDIM/DDPM steps at inference from now on (training is unaffected)."""
        if not 1 <= steps <= self.cfg.num_train_steps:
            raise UserError(
                f"inference steps must be in [1, {self.cfg.num_train_steps}] (the training steps), got {steps}"
            )
        self.cfg = replace(self.cfg, num_inference_steps=steps)

    def set_noise_scale(self, scale: float) -> None:
        """Start sampling from the noise times `scale` from now on (training is unaffected)."""
        self.cfg = replace(self.cfg, noise_scale=scale)  # checked by the config

    @torch.no_grad()
    def sample(
        self,
        cond: torch.Tensor,
        shape: tuple[int, int],
        noise: torch.Tensor | None = None,
        generator: torch.Generator | list[torch.Generator] | None = None,
    ):
        """Denoise from `noise` (B, T, A) (drawn if None), times ``cfg.noise_scale``, to normalised actions (B, T, A).

        `generator`: one for the batch, or a list of B, one per sample, so that a sample's result (including the
        DDPM sampler's per-step noise) does not depend on which other samples share its batch. With
        :attr:`cuda_graphs` set, a DDIM loop on a GPU is recorded once per shape as a CUDA graph and replayed."""
        # diffusers: seconds to import, for the diffusion decoder only
        from diffusers.utils.torch_utils import randn_tensor

        if noise is None:
            noise = randn_tensor((cond.shape[0], *shape), generator=generator, device=cond.device)
        if self.cfg.noise_scale != 1.0:
            noise = noise * self.cfg.noise_scale
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
            out = self.net(x, torch.full((x.shape[0],), t, dtype=torch.long, device=x.device), cond)
            x = self.sample_scheduler.step(out, t, x, generator=generator).prev_sample
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
