"""ICRT, the In-Context Robot Transformer (Fu et al., 2024): the paper's baseline that prompts with a demonstration.

One causal transformer reads the prompt demonstration, then the rollout so far, with action chunking at the token
level as in the paper's appendix (N = ``chunk_len``; chunk k covers steps kN .. kN + N - 1)::

    o_0 a_0 o_1 a_1 ... o_{n-1} a_{n-1} | o'_0 a'_0 o'_1 a'_1 ... o'_k
    '------------ prompt -------------'   '-------- rollout --------'

* o_k: the observation at step kN (every entry and proprioception, through the shared :class:`ObsEncoder`,
  concatenated and projected to one token);
* a_k: the chunk's N actions, normalised, each with a validity flag (a short final chunk is padded), flattened and
  projected to one token;
* plus a learned position and a learned type (prompt or rollout, observation or action).

The output at rollout observation token o'_k predicts that chunk's N actions (an MLP head); training is teacher
forcing with an L1 loss on normalised actions over the rollout's valid steps, so every chunk of a whole rollout
demonstration is a prediction in one pass. No diffusion.

Padding: prompts of different lengths share a batch padded at their end (``valid`` False). No token attends to
padding and a token's position counts only the valid tokens before it, so each sample is computed as if alone.

Inference: :meth:`ICRTModel.encode_context` runs the prompt once and keeps its keys and values
(:class:`ICRTContext`); each :meth:`ICRTModel.predict_action` appends the current observation token to that cache,
predicts the chunk, and remembers the chunk's action token (the predicted actions are the executed ones), which is
appended together with the next observation, so each call is one transformer pass over 1-2 new tokens.

Context limit (``max_tokens``): when a rollout would outgrow it, each sample keeps its whole prompt and the most
recent rollout chunks that fit; that window is run again without the cache (positions re-assigned from the prompt
on, as if the rollout had started at the window), then the cache grows from there. A rollout that stays at the limit
re-runs its window on every call. Training never sees such windows: a training rollout too long to fit after the
prompt only contributes its first chunks. :meth:`ICRTModel.limit_rollout_memory` applies the same window at a chosen
number of chunks (an ablation of what the rollout so far gives ICRT).

Tensor shapes at the boundaries (B: batch, Bp: prompt batch, 1 or B; L: steps; n: chunks; S: tokens; A, D):

* demonstrations (prompt or rollout): ``{"obs": {key: (B, L, ...)}, "action": (B, L, A), "valid": (B, L)}`` raw
* obs at inference: ``{key: (B, 1, ...)}`` raw; predicted actions (B, N, A) raw
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from einops import rearrange, repeat
from torch import nn
from torch.nn import functional as F

from bpp.data.contexts import index_contexts
from bpp.errors import UserError
from bpp.nn.causal import CausalTransformer, KVCache
from bpp.policies.icrt.config import ICRTConfig
from bpp.policies.model import PolicyModel
from bpp.policies.validation import validate_demo_context

# Token types: a segment (prompt or rollout) plus a kind (observation or action), indexing the type embedding.
PROMPT, ROLLOUT = 0, 2
OBS, ACTION = 0, 1


@dataclass
class ICRTContext:
    """The transformer's running context for B rollouts: the prompt, then each rollout as it grows.

    Slots ``[:prompt_slots]`` hold the (padded) prompts; the slots after them hold the rollouts' tokens
    ``o' a' o' a' ... o'``, one pair per chunk, appended in lockstep. A sample's valid rollout slots are always a
    suffix of that region (windows drop the oldest chunks).
    """

    tokens: torch.Tensor  # (B, S, D) every token in context, before positions are added (kept to re-run a window)
    valid: torch.Tensor  # (B, S) bool
    cache: KVCache  # keys and values of `tokens`
    prompt_slots: int
    pending: torch.Tensor | None = None  # (B, 1, D): the last executed action token, appended with the next obs

    def expand_(self, batch: int) -> None:
        """Share a context of batch 1 between `batch` rollouts (in place)."""
        assert self.valid.shape[0] == 1, f"context batch {self.valid.shape[0]} vs observation batch {batch}"
        self.tokens, self.valid = self.tokens.expand(batch, -1, -1), self.valid.expand(batch, -1)
        self.cache = self.cache.expand(batch)
        if self.pending is not None:
            self.pending = self.pending.expand(batch, -1, -1)

    def lengths(self) -> torch.Tensor:
        """(B,) tokens in each sample's sequence, the pending action token included."""
        return self.valid.sum(1) + (self.pending is not None)


class ICRTModel(PolicyModel):
    """In-Context Robot Transformer (tensor-only; :class:`bpp.policies.agent.PolicyAgent` wraps it for rollouts)."""

    method = "icrt"
    context_kind = "demo"

    def __init__(self, cfg: ICRTConfig, stats: Mapping[str, Mapping[str, list[float]]]):
        super().__init__(cfg, stats)
        N, D = cfg.chunk_len, cfg.dim
        self.obs_proj = nn.Linear(sum(self.obs_encoder.dims), D)
        self.action_proj = nn.Linear(N * (self.action_dim + 1), D)  # N actions, each with its validity flag
        self.type_embed = nn.Parameter(torch.randn(4, D) * 0.02)
        self.pos_embed = nn.Parameter(torch.randn(cfg.max_tokens, D) * 0.02)
        self.transformer = CausalTransformer(D, cfg.layers, cfg.heads, cfg.mlp_dim, cfg.dropout)
        self.head = nn.Sequential(nn.Linear(D, D), nn.GELU(), nn.Linear(D, N * self.action_dim))
        self.rollout_memory = 0
        """Rollout chunks an inference sees, its own included (0: all that fit in ``max_tokens``); see
        :meth:`limit_rollout_memory`."""

    def limit_rollout_memory(self, chunks: int) -> None:
        """From now on each inference sees the prompt and only the last `chunks` rollout chunks, its own included
        (0: all that fit), as a rollout past the context limit does: an evaluation-time ablation of what the rollout so
        far gives ICRT (training always sees whole rollouts)."""
        if chunks < 0:
            raise UserError(f"rollout memory must be >= 0 chunks (0: all that fit), got {chunks}")
        self.rollout_memory = chunks

    # ----------------------------------------------------------------- tokens
    def obs_tokens(self, obs: Mapping[str, torch.Tensor], segment: int) -> torch.Tensor:
        """Raw observations ``{key: (B, n, ...)}``, one per chunk -> observation tokens (B, n, D), no position."""
        features = torch.cat(self.obs_encoder(obs), dim=-1)
        return self.obs_proj(features) + self.type_embed[segment + OBS]

    def action_tokens(
        self, actions: torch.Tensor, valid: torch.Tensor, segment: int, origin: torch.Tensor | None
    ) -> torch.Tensor:
        """Raw actions (B, L, A) with `valid` (B, L) -> one token per chunk of N steps (B, ceil(L / N), D).

        `origin` (B, L or 1, P): where relative actions start (``cfg.action_relative_to``; None if absolute).
        """
        N = self.cfg.chunk_len
        a = self.normalize_actions(actions, origin) * valid[..., None]
        a = torch.cat([a, valid[..., None].float()], dim=-1)
        a = F.pad(a, (0, 0, 0, -a.shape[1] % N))
        return self.action_proj(rearrange(a, "b (n t) c -> b n (t c)", t=N)) + self.type_embed[segment + ACTION]

    def demo_tokens(self, demo: Mapping, segment: int) -> tuple[torch.Tensor, torch.Tensor]:
        """A demonstration (B, L) -> its interleaved tokens ``o_0 a_0 o_1 a_1 ...`` (B, 2n, D) and their validity."""
        N = self.cfg.chunk_len
        valid = demo["valid"].bool()
        chunk_obs = self.chunk_obs(demo, N)
        obs = self.obs_tokens(chunk_obs, segment)
        origin = self.chunk_origins(chunk_obs, N, valid.shape[1])
        actions = self.action_tokens(demo["action"], valid, segment, origin)
        tokens = rearrange(torch.stack([obs, actions], dim=2), "b n two d -> b (n two) d")
        return tokens, repeat(valid[:, ::N], "b n -> b (n two)", two=2)  # a chunk exists where its first step does

    def run(
        self, tokens: torch.Tensor, valid: torch.Tensor, cache: KVCache | None = None, attention: list | None = None
    ) -> tuple[torch.Tensor, KVCache]:
        """Tokens (B, S_new, D) after the cached ones -> outputs (B, S_new, D) and the extended cache.

        Each token's position is the number of valid tokens before it in its own sample (padding takes its
        neighbour's position; nothing attends to it). `attention`: see :class:`~bpp.nn.causal.CausalTransformer`.
        """
        start = 0 if cache is None else cache.valid.sum(1, keepdim=True)
        positions = (start + valid.cumsum(1) - 1).clamp_min(0)
        if not torch.compiler.is_compiling():  # a host read; training's sequences fit by construction
            assert int(positions.max()) < self.cfg.max_tokens, "sequence longer than max_tokens"
        return self.transformer(tokens + self.pos_embed[positions], valid, cache, attention)

    # ------------------------------------------------------------------ train
    def compute_loss(
        self, batch: Mapping, generator: torch.Generator | None = None, noise: Mapping | None = None
    ) -> torch.Tensor:
        """Mean L1 error of the normalised actions over the valid rollout steps (teacher forcing).

        batch: ``{"context": prompts (G, Lp), "context_index": (B,), "obs": {key: (B, L, ...)}, "action": (B, L, A),
        "valid": (B, L)}``, B whole demonstrations padded to the longest, rollout i of the task of prompt
        ``context_index[i]``. `generator` and `noise` are unused: the loss draws no noise (dropout draws
        from the global generator, which the training loop seeds per step).
        """
        prompt = batch["context"]
        if "context_index" in batch and prompt["valid"].shape[0] > 1:  # several tasks: each rollout its own prompt
            prompt = index_contexts(prompt, batch["context_index"])
        ctx = self.encode_context(prompt)
        # A rollout longer than what fits after the batch's longest prompt is cut: only its first chunks are learned
        # from. Eager, the steps after the cut are not run at all; a compiled loss keeps its shapes (reading the cut
        # on the host would split its graph) and masks them: no valid token attends to them, so the loss is the same.
        fits = (self.cfg.max_tokens - ctx.valid.sum(1).max()) // 2 * self.cfg.chunk_len
        obs, actions, valid = batch["obs"], batch["action"], batch["valid"].bool()
        if torch.compiler.is_compiling():
            valid = valid & (torch.arange(valid.shape[1], device=valid.device) < fits)
        else:
            steps = int(fits)
            obs = {k: v[:, :steps] for k, v in obs.items()}
            actions, valid = actions[:, :steps], valid[:, :steps]
        predicted = rearrange(
            self.rollout_chunks(ctx, {"obs": obs, "action": actions, "valid": valid}), "b n t a -> b (n t) a"
        )
        target = self.normalize_actions(actions, self.chunk_origins(obs, self.cfg.chunk_len))
        error = (predicted[:, : target.shape[1]] - target).abs() * valid[..., None]
        return error.sum() / (valid.sum() * self.action_dim).clamp_min(1)

    def rollout_chunks(self, ctx: ICRTContext, rollout: Mapping) -> torch.Tensor:
        """Teacher forcing: whole rollouts (B, L) after the encoded prompts -> each chunk's predicted normalised
        actions (B, n, N, A), chunk k seeing the prompt, observations 0..k and the actions of chunks before k.

        `ctx` is not modified; a prompt of batch 1 is shared by the B rollouts (run once, not B times).
        """
        tokens, valid = self.demo_tokens(rollout, ROLLOUT)
        cache = ctx.cache if ctx.valid.shape[0] == tokens.shape[0] else ctx.cache.expand(tokens.shape[0])
        out, _ = self.run(tokens, valid, cache)
        return rearrange(self.head(out[:, ::2]), "b n (t a) -> b n t a", t=self.cfg.chunk_len)

    # -------------------------------------------------------------- inference
    def check_action_steps(self, n_action_steps: int) -> None:
        """All N actions of a chunk must run: the context records each chunk's N predicted actions as executed."""
        if n_action_steps != self.cfg.chunk_len:
            raise UserError(
                f"ICRT executes all N={self.cfg.chunk_len} actions of each chunk (its context records them as "
                f"executed, so replanning earlier would feed it actions that never ran); got n_action_steps="
                f"{n_action_steps}"
            )

    def context_spec(self) -> dict:
        """Training batches: a prompt demonstration and B whole demonstrations of the same task."""
        return {
            "samples": "episodes",
            "max_prompt_steps": self.cfg.max_prompt_steps,
            "context_obs_stride": self.cfg.chunk_len,
            "max_episode_steps": (self.cfg.max_tokens // 2 - 1) * self.cfg.chunk_len,  # fits after a 1-chunk prompt
        }

    def validate_context(self, prompt: Mapping) -> dict:
        """Check a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}`` and batch it; clear errors if bad."""
        cfg = self.cfg
        why = (
            f" (its context holds {cfg.max_tokens} tokens, 2 per chunk of {cfg.chunk_len} steps, and keeps room "
            f"for {cfg.min_rollout_chunks} rollout chunks)"
        )
        return validate_demo_context(
            prompt, cfg.obs, self.normalizer, cfg.action_key, cfg.chunk_len, cfg.max_prompt_steps, why
        )

    def encode_context(self, prompt: Mapping) -> ICRTContext:
        """Run prompts (Bp, L) through the transformer once: the context every rollout step extends."""
        tokens, valid = self.demo_tokens(prompt, PROMPT)
        _, cache = self.run(tokens, valid)
        return ICRTContext(tokens, valid, cache, tokens.shape[1])

    @torch.no_grad()
    def predict_action(
        self,
        obs: Mapping[str, torch.Tensor],
        ctx: ICRTContext,
        noise: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        return_attention: bool = False,
    ) -> dict[str, torch.Tensor]:
        """The next chunk's N actions (B, N, A) raw, from the observation ``{key: (B, 1, ...)}`` at its first step.

        Extends `ctx` by this chunk (it must be called once per N executed steps, as :class:`PolicyAgent` does
        with ``n_action_steps = N``). Deterministic: `noise` and `generator` are unused. With `return_attention`,
        also ``"attention"`` (B, n_chunks + 1): the observation token's attention, averaged over layers and heads,
        summed per prompt chunk (its observation and action tokens) in columns 1.., and on the rollout so far (this
        observation's token included) in column 0.
        """
        batch = next(iter(obs.values())).shape[0]
        if ctx.valid.shape[0] != batch:
            ctx.expand_(batch)
        new = self.obs_tokens(obs, ROLLOUT)
        if ctx.pending is not None:
            new = torch.cat([ctx.pending, new], dim=1)
        new_valid = torch.ones(new.shape[:2], dtype=torch.bool, device=new.device)
        tokens, valid = torch.cat([ctx.tokens, new], dim=1), torch.cat([ctx.valid, new_valid], dim=1)
        attention = [] if return_attention else None
        if bool((valid[:, ctx.prompt_slots :].sum(1) > self.rollout_room(valid, ctx.prompt_slots)).any()):
            tokens, valid = self.window(tokens, valid, ctx.prompt_slots)
            out, ctx.cache = self.run(tokens, valid, attention=attention)
        else:
            out, ctx.cache = self.run(new, new_valid, ctx.cache, attention)
        ctx.tokens, ctx.valid = tokens, valid
        chunk = rearrange(self.head(out[:, -1]), "b (t a) -> b t a", t=self.cfg.chunk_len)
        origin = self.action_origin(obs)
        actions = self.unnormalize_actions(chunk, origin)
        executed = torch.ones(actions.shape[:2], dtype=torch.bool, device=actions.device)
        ctx.pending = self.action_tokens(actions, executed, ROLLOUT, origin)
        if attention is None:
            return {"action": actions}
        return {"action": actions, "attention": self.prompt_attention(torch.stack(attention).mean(0), ctx.prompt_slots)}

    @staticmethod
    def prompt_attention(weights: torch.Tensor, prompt_slots: int) -> torch.Tensor:
        """Attention over the token slots (B, S), prompt first -> (B, 1 + prompt_slots // 2): the rollout's share,
        then each prompt chunk's (two slots, observation and action, per chunk; padding gets none)."""
        chunks = weights[:, :prompt_slots].unflatten(1, (-1, 2)).sum(-1)
        return torch.cat([weights[:, prompt_slots:].sum(1, keepdim=True), chunks], dim=1)

    def rollout_room(self, valid: torch.Tensor, prompt_slots: int) -> torch.Tensor:
        """(B,) rollout slots each sample may keep after its prompt: whole chunks that fit in ``max_tokens`` with the
        newest one's action token still to come (at most :attr:`rollout_memory` chunks, where set)."""
        room = (self.cfg.max_tokens - valid[:, :prompt_slots].sum(1)) // 2 * 2 - 1
        return room.clamp_max(2 * self.rollout_memory - 1) if self.rollout_memory else room

    def window(self, tokens: torch.Tensor, valid: torch.Tensor, prompt_slots: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep each sample's prompt and its most recent rollout chunks that fit in ``max_tokens`` (at most
        :attr:`rollout_memory` of them, where set).

        tokens (B, S, D), valid (B, S): the prompts, then rollout slots ``o' a' ... o'`` ending with the newest
        observation (whose action token is still to come). Returns the shortened tokens and validity. Because each
        sample's valid rollout slots are a suffix, its window is a shorter suffix; slots that no sample keeps go.
        """
        keep = torch.minimum(self.rollout_room(valid, prompt_slots), valid[:, prompt_slots:].sum(1))
        assert int(keep.min()) >= 1, "a prompt leaves no room for the rollout (validate_context should refuse it)"
        region = tokens.shape[1] - prompt_slots
        first = region - int(keep.max())  # even: a window starts at an observation token
        from_end = torch.arange(region - first - 1, -1, -1, device=valid.device)
        rollout_valid = from_end[None] < keep[:, None]
        tokens = torch.cat([tokens[:, :prompt_slots], tokens[:, prompt_slots + first :]], dim=1)
        return tokens, torch.cat([valid[:, :prompt_slots], rollout_valid], dim=1)
