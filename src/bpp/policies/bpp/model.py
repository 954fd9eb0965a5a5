"""The BPP network: prompt chunking + attention pooling, a cross-attention prompt encoder, a diffusion decoder.

Tensor shapes at the boundaries (B: batch, Bp: prompt batch, 1 or B; L: prompt steps; n: chunks; To, T, A):

* prompt: ``{"obs": {key: (Bp, L, ...)}, "action": (Bp, L, A), "valid": (Bp, L) bool}`` raw (unnormalised)
* obs: ``{key: (B, To, ...)}`` raw; action: (B, T, A) raw
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from einops import rearrange, repeat
from torch import nn

from bpp.data.prompt_dataset import DataSpec
from bpp.nn.attention import AttentionPooling, CrossAttentionDecoder
from bpp.policies.bpp.config import BPPConfig
from bpp.policies.common import DiffusionHead, Normalizer, ObsEncoder


class PromptError(ValueError):
    """A prompt that this model cannot use; the message says what was expected."""


@dataclass
class PromptContext:
    """An encoded prompt: computed once per rollout and reused by every inference call."""

    tokens: torch.Tensor  # (Bp, M, D)
    valid: torch.Tensor  # (Bp, M) bool
    token_chunk: torch.Tensor  # (M,) long: the prompt chunk each token belongs to, -1 for attention sinks
    num_chunks: int

    def expand(self, batch: int) -> PromptContext:
        if self.tokens.shape[0] == batch:
            return self
        assert self.tokens.shape[0] == 1, f"prompt batch {self.tokens.shape[0]} vs observation batch {batch}"
        return PromptContext(
            self.tokens.expand(batch, -1, -1), self.valid.expand(batch, -1), self.token_chunk, self.num_chunks
        )


class BPPModel(nn.Module):
    """Behavior Prompting Policy (tensor-only; :class:`bpp.policies.agent.PolicyAgent` wraps it for rollouts)."""

    method = "bpp"
    context_kind = "demo"

    def __init__(self, cfg: BPPConfig, stats: Mapping[str, Mapping[str, list[float]]]):
        super().__init__()
        self.cfg = cfg
        obs_cfg, pcfg, h = cfg.obs, cfg.prompt, cfg.horizons
        self.normalizer = Normalizer(stats, [*obs_cfg.lowdim_keys, *obs_cfg.proprio_keys, cfg.action_key])
        self.action_dim = self.normalizer.width(cfg.action_key)
        self.obs_encoder = ObsEncoder(obs_cfg, self.normalizer)
        self.entries = obs_cfg.entries
        D = cfg.dim
        self.entry_proj = nn.ModuleList([nn.Linear(f, D) for f in self.obs_encoder.dims])
        self.entry_embed = nn.Parameter(torch.randn(len(self.entries) + 1, D) * 0.02)  # + one for actions
        # Only modules that are used get created: DDP requires every parameter to receive a gradient.
        self.action_proj = nn.Linear(pcfg.chunk_len * (self.action_dim + 1), D) if pcfg.use_action else None
        proprio = set(obs_cfg.proprio_keys)
        self.prompt_entries = [
            i
            for i, name in enumerate(self.entries)
            if (name in proprio and pcfg.use_proprio) or (name not in proprio and pcfg.use_obs)
        ]
        self.pool = AttentionPooling(D, cfg.heads) if pcfg.pooling != "none" else None
        self.chunk_pos = nn.Parameter(torch.randn(pcfg.max_chunks, D) * 0.02)
        self.sinks = nn.Parameter(torch.randn(pcfg.num_sinks, D) * 0.02)
        self.obs_pos = nn.Parameter(torch.randn(h.n_obs_steps * len(self.entries), D) * 0.02)
        self.prompt_encoder = CrossAttentionDecoder(D, cfg.layers, cfg.heads, cfg.mlp_dim, cfg.dropout)
        cond_dim = h.n_obs_steps * (len(self.entries) * D + sum(self.obs_encoder.dims))
        self.head = DiffusionHead(cfg.diffusion, self.action_dim, cond_dim)

    # ------------------------------------------------------------------ prompt
    def encode_prompt(self, prompt: Mapping) -> PromptContext:
        """Cut the prompt into chunks of Δt steps and turn each into tokens (pooled per chunk, by default)."""
        dt = self.cfg.prompt.chunk_len
        actions, valid = prompt["action"], prompt["valid"].bool()
        bp, steps = valid.shape
        n = -(-steps // dt)
        if n > self.cfg.prompt.max_chunks:
            raise ValueError(f"prompt of {steps} steps exceeds the model's limit of {self.cfg.prompt.max_steps}")
        chunk_valid = valid[:, ::dt]  # (Bp, n): a chunk exists where its first step does
        modality = []
        if self.prompt_entries:
            features = self.obs_encoder({k: v[:, ::dt] for k, v in prompt["obs"].items()})
            for i in self.prompt_entries:
                modality.append(self.entry_proj[i](features[i]) + self.entry_embed[i])
        if self.cfg.prompt.use_action:
            pad = n * dt - steps
            a = self.normalizer.normalize(self.cfg.action_key, actions) * valid[..., None]
            a = torch.cat([a, valid[..., None].float()], dim=-1)
            a = nn.functional.pad(a, (0, 0, 0, pad))
            a = rearrange(a, "b (n dt) c -> b n (dt c)", dt=dt)
            modality.append(self.action_proj(a) + self.entry_embed[-1])
        tokens = torch.stack(modality, dim=2)  # (Bp, n, E', D)
        pooling = self.cfg.prompt.pooling
        if pooling == "all":
            tokens = self.pool(rearrange(tokens, "b n e d -> (b n) e d")).view(bp, n, 1, -1)
        elif pooling == "obs" and self.cfg.prompt.use_action and tokens.shape[2] > 1:
            pooled = self.pool(rearrange(tokens[:, :, :-1], "b n e d -> (b n) e d")).view(bp, n, 1, -1)
            tokens = torch.cat([pooled, tokens[:, :, -1:]], dim=2)
        elif pooling == "obs":
            tokens = self.pool(rearrange(tokens, "b n e d -> (b n) e d")).view(bp, n, 1, -1)
        per_chunk = tokens.shape[2]
        tokens = tokens + self.chunk_pos[:n, None]
        tokens = rearrange(tokens, "b n k d -> b (n k) d")
        token_valid = repeat(chunk_valid, "b n -> b (n k)", k=per_chunk)
        sinks = self.sinks.expand(bp, -1, -1)
        token_chunk = torch.cat([torch.full((len(self.sinks),), -1), torch.arange(n).repeat_interleave(per_chunk)]).to(
            tokens.device
        )
        return PromptContext(
            torch.cat([sinks, tokens], dim=1),
            torch.cat([torch.ones(bp, len(self.sinks), dtype=torch.bool, device=valid.device), token_valid], dim=1),
            token_chunk,
            n,
        )

    # ------------------------------------------------------------- conditioning
    def condition(self, obs: Mapping[str, torch.Tensor], ctx: PromptContext, return_attention: bool = False):
        """Observation history + encoded prompt -> conditioning vector (B, C) [and cross-attention maps]."""
        features = self.obs_encoder(obs)  # list of (B, To, F_e)
        tokens = torch.stack([proj(f) for proj, f in zip(self.entry_proj, features, strict=True)], dim=2)
        tokens = rearrange(tokens, "b t e d -> b (t e) d") + self.obs_pos
        ctx = ctx.expand(tokens.shape[0])
        out, attentions = self.prompt_encoder(tokens, ctx.tokens, ctx.valid, return_attention)
        cond = torch.cat([out.flatten(1), torch.cat(features, dim=-1).flatten(1)], dim=-1)
        return cond, attentions

    # ------------------------------------------------------------------ train
    def forward(self, batch: Mapping, generator: torch.Generator | None = None) -> torch.Tensor:
        """The training loss (``forward`` so that DDP's gradient hooks see it)."""
        return self.compute_loss(batch, generator)

    def compute_loss(self, batch: Mapping, generator: torch.Generator | None = None) -> torch.Tensor:
        ctx = self.encode_prompt(batch["context"])
        cond, _ = self.condition(batch["obs"], ctx)
        actions = self.normalizer.normalize(self.cfg.action_key, batch["action"])
        return self.head.loss(actions, cond, generator)

    # -------------------------------------------------------------- inference
    def obs_keys(self) -> list[str]:
        """Per-step observation keys the policy reads (and a prompt demonstration must provide)."""
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
            context="demo",
            max_prompt_steps=self.cfg.prompt.max_steps,
        )

    def validate_context(self, prompt: Mapping) -> dict:
        """Check a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` and batch it; clear errors if bad."""
        if not isinstance(prompt, Mapping) or "obs" not in prompt or "action" not in prompt:
            raise PromptError("a prompt must be a dict with 'obs' (a dict of per-step arrays) and 'action'")
        actions = np.asarray(prompt["action"], dtype=np.float32)
        if actions.ndim != 2 or actions.shape[1] != self.action_dim:
            raise PromptError(
                f"prompt actions must have shape (steps, {self.action_dim}) as in training, got {actions.shape}"
            )
        steps = len(actions)
        dt = self.cfg.prompt.chunk_len
        if steps < dt:
            raise PromptError(f"prompt has {steps} steps; at least one chunk of {dt} steps is needed")
        if steps > self.cfg.prompt.max_steps:
            raise PromptError(f"prompt has {steps} steps; this model accepts at most {self.cfg.prompt.max_steps}")
        if not np.all(np.isfinite(actions)):
            raise PromptError("prompt actions contain NaN or infinite values")
        obs = {}
        for key in self.obs_keys():
            if key not in prompt["obs"]:
                raise PromptError(f"prompt obs lacks {key!r}; expected keys {self.obs_keys()}")
            value = np.asarray(prompt["obs"][key])
            if len(value) != steps:
                raise PromptError(f"prompt obs {key!r} has {len(value)} steps, actions have {steps}")
            if key in self.cfg.obs.image_keys:
                size = self.cfg.obs.image_size
                if value.shape[1:] != (size, size, 3):
                    raise PromptError(f"prompt images {key!r} must be (steps, {size}, {size}, 3), got {value.shape}")
            else:
                width = self.normalizer.width(key)
                if value.ndim != 2 or value.shape[1] != width:
                    raise PromptError(f"prompt obs {key!r} must be (steps, {width}), got {value.shape}")
                if not np.all(np.isfinite(value)):
                    raise PromptError(f"prompt obs {key!r} contains NaN or infinite values")
            obs[key] = value[None]
        return {"obs": obs, "action": actions[None], "valid": np.ones((1, steps), dtype=bool)}

    def encode_context(self, context: Mapping) -> PromptContext:
        return self.encode_prompt(context)

    @torch.no_grad()
    def predict_action(
        self,
        obs: Mapping[str, torch.Tensor],
        ctx: PromptContext,
        noise: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        return_attention: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Action chunk (B, T, A) in raw units; with `return_attention`, also the prompt attention per chunk."""
        cond, attentions = self.condition(obs, ctx, return_attention)
        shape = (self.cfg.horizons.horizon, self.action_dim)
        actions = self.normalizer.unnormalize(self.cfg.action_key, self.head.sample(cond, shape, noise, generator))
        out = {"action": actions}
        if return_attention:
            out["attention"] = self.chunk_attention(attentions, ctx)
        return out

    @staticmethod
    def chunk_attention(attentions: list[torch.Tensor], ctx: PromptContext) -> torch.Tensor:
        """Average cross-attention (over layers and query tokens) summed per prompt chunk: (B, n_chunks + 1).

        Column 0 is the attention-sink mass; column i + 1 is chunk i.
        """
        weights = torch.stack(attentions).mean(dim=(0, 2))  # (B, M)
        index = (ctx.token_chunk + 1).expand_as(weights)
        out = torch.zeros(weights.shape[0], ctx.num_chunks + 1, device=weights.device)
        return out.scatter_add_(1, index, weights)
