"""The BPP network: prompt chunking + attention pooling, a cross-attention prompt encoder, a diffusion decoder.

Tensor shapes at the boundaries (B: batch, Bp: prompt batch, 1 or B; L: prompt steps; n: chunks; To, T, A):

* prompt: ``{"obs": {key: (Bp, L, ...)}, "action": (Bp, L, A), "valid": (Bp, L) bool}`` raw (unnormalised)
* obs: ``{key: (B, To, ...)}`` raw; action: (B, T, A) raw
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from einops import rearrange, repeat
from torch import nn

from bpp.errors import UserError
from bpp.nn.attention import AttentionPooling, CrossAttentionDecoder
from bpp.nn.lowdim import FourierFeatures
from bpp.policies.bpp.config import BPPConfig
from bpp.policies.model import ContextDiffusionPolicy
from bpp.policies.validation import PromptError as PromptError  # raised by validate_context; importable from here
from bpp.policies.validation import validate_demo_context


@dataclass
class PromptContext:
    """An encoded prompt: computed once per rollout and reused by every inference call."""

    tokens: torch.Tensor  # (Bp, M, D)
    valid: torch.Tensor  # (Bp, M) bool
    token_chunk: torch.Tensor  # (M,) long: the prompt chunk each token belongs to, -1 for attention sinks
    num_chunks: int
    index: torch.Tensor | None = None
    """(B,) long, if set: sample i reads prompt ``index[i]`` of the Bp (see :meth:`select`); else one per sample."""

    def select(self, index: torch.Tensor) -> PromptContext:
        """One prompt per sample: sample i takes prompt ``index[i]`` (index (B,) into the Bp prompts). The prompts
        are not copied per sample: the prompt encoder projects each once and hands it to its samples."""
        return PromptContext(self.tokens, self.valid, self.token_chunk, self.num_chunks, index)

    @staticmethod
    def merge(contexts: list[PromptContext]) -> PromptContext:
        """Encoded prompts of different lengths -> one batch: tokens past a prompt's end are padded and invalid, so
        attention ignores them (the longest prompt's chunk map covers every shorter one's)."""
        assert all(c.index is None for c in contexts), "merge whole prompts, not selections of them"
        longest = max(contexts, key=lambda c: c.tokens.shape[1])
        m = longest.tokens.shape[1]

        def pad(x: torch.Tensor) -> torch.Tensor:
            extra = m - x.shape[1]
            return torch.cat([x, x.new_zeros((x.shape[0], extra, *x.shape[2:]))], dim=1) if extra else x

        return PromptContext(
            torch.cat([pad(c.tokens) for c in contexts]),
            torch.cat([pad(c.valid) for c in contexts]),
            longest.token_chunk,
            longest.num_chunks,
        )

    def expand(self, batch: int) -> PromptContext:
        if self.index is not None:
            assert len(self.index) == batch, f"{len(self.index)} selected prompts vs observation batch {batch}"
            return self
        if self.tokens.shape[0] == batch:
            return self
        assert self.tokens.shape[0] == 1, f"prompt batch {self.tokens.shape[0]} vs observation batch {batch}"
        return PromptContext(
            self.tokens.expand(batch, -1, -1), self.valid.expand(batch, -1), self.token_chunk, self.num_chunks
        )


class BPPModel(ContextDiffusionPolicy):
    """Behavior Prompting Policy (tensor-only; :class:`bpp.policies.agent.PolicyAgent` wraps it for rollouts)."""

    method = "bpp"
    context_kind = "demo"

    def __init__(self, cfg: BPPConfig, stats: Mapping[str, Mapping[str, list[float]]]):
        super().__init__(cfg, stats)
        obs_cfg, pcfg, h = cfg.obs, cfg.prompt, cfg.horizons
        self.entries = obs_cfg.entries
        D = cfg.dim
        self.entry_proj = nn.ModuleList([nn.Linear(f, D) for f in self.obs_encoder.dims])
        self.entry_embed = nn.Parameter(torch.randn(len(self.entries) + 1, D) * 0.02)  # + one for actions
        # Only modules that are used get created: DDP requires every parameter to receive a gradient.
        self.action_fourier, self.action_proj = None, None
        if pcfg.use_action:
            width = self.action_dim
            if pcfg.action_fourier_octaves:  # a nonlinear embedding of the chunk's actions (see bpp.nn.lowdim)
                self.action_fourier = FourierFeatures(pcfg.action_fourier_octaves)
                width = self.action_fourier.out_dim(width)
            flat = pcfg.chunk_len * (width + 1)  # + a validity flag per step
            self.action_proj = (
                nn.Sequential(nn.Linear(flat, D), nn.GELU(), nn.Linear(D, D))
                if self.action_fourier is not None
                else nn.Linear(flat, D)
            )
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
        if pcfg.rollout_memory:  # created only when used (see above)
            self.memory_pos = nn.Parameter(torch.randn(pcfg.rollout_memory * len(self.entries), D) * 0.02)
        self.prompt_encoder = CrossAttentionDecoder(D, cfg.layers, cfg.heads, cfg.mlp_dim, cfg.dropout)
        self.build_head(h.n_obs_steps * len(self.entries) * D)  # the prompt encoder's outputs for To steps

    # ------------------------------------------------------------------ prompt
    def encode_prompt(self, prompt: Mapping) -> PromptContext:
        """Cut the prompt into chunks of Δt steps and turn each into tokens (pooled per chunk, by default)."""
        dt = self.cfg.prompt.chunk_len
        actions, valid = prompt["action"], prompt["valid"].bool()
        bp, steps = valid.shape
        n = -(-steps // dt)
        if n > self.cfg.prompt.max_chunks:
            raise UserError(f"prompt of {steps} steps exceeds the model's limit of {self.cfg.prompt.max_steps}")
        chunk_valid = valid[:, ::dt]  # (Bp, n): a chunk exists where its first step does
        modality = []
        chunk_obs = self.chunk_obs(prompt, dt)
        if self.prompt_entries:
            features = self.obs_encoder(chunk_obs)
            for i in self.prompt_entries:
                modality.append(self.entry_proj[i](features[i]) + self.entry_embed[i])
        if self.cfg.prompt.use_action:
            pad = n * dt - steps
            a = self.normalize_actions(actions, self.chunk_origins(chunk_obs, dt, steps))
            if self.action_fourier is not None:
                a = self.action_fourier(a)
            a = a * valid[..., None]
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
        device = tokens.device  # made there: a compiled loss on a GPU must read no CPU tensor (see DiffusionHead)
        token_chunk = torch.cat(
            [
                torch.full((len(self.sinks),), -1, device=device),
                torch.arange(n, device=device).repeat_interleave(per_chunk),
            ]
        )
        return PromptContext(
            torch.cat([sinks, tokens], dim=1),
            torch.cat([torch.ones(bp, len(self.sinks), dtype=torch.bool, device=valid.device), token_valid], dim=1),
            token_chunk,
            n,
        )

    # ------------------------------------------------------------- conditioning
    def condition(self, obs: Mapping[str, torch.Tensor], ctx: PromptContext, return_attention: bool = False):
        """Observation history + encoded prompt -> conditioning vector (B, C) [and cross-attention maps].

        With a rollout memory of K steps, `obs` holds K + To steps, the memory's first: its tokens attend to the
        prompt and are attended to by the current ones; the decoder reads the To current steps' outputs."""
        features = self.obs_encoder(obs)  # list of (B, K + To, F_e)
        tokens = torch.stack([proj(f) for proj, f in zip(self.entry_proj, features, strict=True)], dim=2)
        tokens = rearrange(tokens, "b t e d -> b (t e) d")
        memory = self.cfg.prompt.rollout_memory
        pos = torch.cat([self.memory_pos, self.obs_pos]) if memory else self.obs_pos
        ctx = ctx.expand(tokens.shape[0])
        out, attentions = self.prompt_encoder(tokens + pos, ctx.tokens, ctx.valid, return_attention, ctx.index)
        current = len(self.obs_pos)  # the To steps' tokens come last
        out, attentions = out[:, -current:], [a[:, -current:] for a in attentions]
        features = [f[:, memory:] for f in features]
        return torch.cat([out.flatten(1), self.flatten_obs(features)], dim=-1), attentions

    # -------------------------------------------------------------- inference
    def context_spec(self) -> dict:
        p = self.cfg.prompt
        return {"max_prompt_steps": p.max_steps, "context_obs_stride": p.chunk_len, "memory_offsets": p.memory_offsets}

    def validate_context(self, prompt: Mapping) -> dict:
        """Check a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` and batch it; clear errors if bad."""
        cfg = self.cfg
        return validate_demo_context(
            prompt, cfg.obs, self.normalizer, cfg.action_key, cfg.prompt.chunk_len, cfg.prompt.max_steps
        )

    def encode_context(self, context: Mapping) -> PromptContext:
        return self.encode_prompt(context)

    @staticmethod
    def merge_contexts(contexts: list[PromptContext]) -> PromptContext:
        return PromptContext.merge(contexts)

    @staticmethod
    def select_context(ctx: PromptContext, index: torch.Tensor) -> PromptContext:
        return ctx.select(index)

    @staticmethod
    def context_attention(attentions: list[torch.Tensor], ctx: PromptContext) -> torch.Tensor:
        """Average cross-attention (over layers and query tokens) summed per prompt chunk: (B, n_chunks + 1).

        Column 0 is the attention-sink mass; column i + 1 is chunk i.
        """
        weights = torch.stack(attentions).mean(dim=(0, 2))  # (B, M)
        index = (ctx.token_chunk + 1).expand_as(weights)
        out = torch.zeros(weights.shape[0], ctx.num_chunks + 1, device=weights.device)
        return out.scatter_add_(1, index, weights)
