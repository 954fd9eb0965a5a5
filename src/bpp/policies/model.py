"""The model bases every method builds on: :class:`PolicyModel` (normaliser, observation encoder, action
normalisation, the training batches wanted) and :class:`ContextDiffusionPolicy` (the diffusion decoder conditioned
on observations plus an encoded task context); and helpers over whole models."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from bpp.data.spec import DataSpec
from bpp.errors import UserError
from bpp.policies.diffusion import DiffusionHead
from bpp.policies.normalizer import Normalizer
from bpp.policies.observation import ObsEncoder


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
            raise UserError(
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
                raise UserError(f"action_relative_to {origin!r} must be an observed low-dimensional key")
            if self.normalizer.width(origin) > self.action_dim:
                raise UserError(f"action_relative_to {origin!r} is wider than the actions ({self.action_dim})")
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
        raise UserError(f"{type(self).__name__} has no diffusion decoder: it takes no inference steps")

    def set_noise_scale(self, scale: float) -> None:
        """Sample from the decoder's noise times `scale` from now on; models without a diffusion decoder refuse."""
        raise UserError(f"{type(self).__name__} has no diffusion decoder: it samples no noise to scale")

    def check_action_steps(self, n_action_steps: int) -> None:
        """Refuse (ValueError) an agent that would execute `n_action_steps` actions of each predicted chunk."""
        h = self.cfg.horizons
        if not 1 <= n_action_steps <= h.horizon - h.n_obs_steps + 1:
            raise UserError(
                f"n_action_steps must be in [1, {h.horizon - h.n_obs_steps + 1}] (horizon T={h.horizon}, "
                f"To={h.n_obs_steps}), got {n_action_steps}"
            )

    @staticmethod
    def merge_contexts(contexts: list):
        """Encoded contexts of separately started rollouts -> one batch, for a joint inference call (a policy
        server's concurrent clients); None where this model's contexts cannot be joined (they hold state that each
        inference call extends, as ICRT's key-value cache does)."""
        return None

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

    def set_noise_scale(self, scale: float) -> None:
        self.head.set_noise_scale(scale)

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
    def merge_contexts(contexts: list) -> torch.Tensor:
        return torch.cat(contexts)

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
