"""The inference agent every evaluator and interface uses: numpy in, numpy out, one or many rollouts in lockstep.

It owns what a rollout needs beyond the network: the task context encoded once at :meth:`reset` (for BPP, the
prompt's chunk embeddings), the observation history (To steps, and the earlier ones a model reads as its rollout
memory; the first observation repeated at the start), the receding-horizon action queue (Ta of each predicted
T-step chunk are executed), and one noise generator per rollout, seeded by the caller, so that every method sees
identical seeds and a rollout does not depend on which other rollouts share its batch.

Any model that implements :class:`bpp.policies.registry.PolicyModelContract` plugs in; the agent uses nothing else.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from bpp.data.contexts import collate_contexts
from bpp.data.spec import DataSpec
from bpp.policies.diffusion import DiffusionHead
from bpp.policies.registry import PolicyModelContract
from bpp.utils import to_torch


class PolicyAgent:
    """Wraps a tensor-only policy model for closed-loop control.

    Args:
        model: a policy model (see the module docstring for the contract).
        device: where to run the model.
        n_action_steps: actions executed per inference (default: the model's Ta).
        num_inference_steps: denoising steps per inference for models with a diffusion decoder (default: the
            model's own); fewer is faster, more may be more precise.
        noise_scale: a diffusion decoder's initial noise times this (default: the model's own, see
            :attr:`~bpp.policies.config.DiffusionConfig.noise_scale`).
        record_attention: keep the prompt attention of every inference in :attr:`attention_log`
            (models that have none ignore it).
        cuda_graphs: on a GPU, replay a diffusion decoder's DDIM sampling loop from a CUDA graph (the same
            numbers; 35.9 against 95.7 ms per inference call for the paper preset on an H100: BENCHMARKS.md).
    """

    def __init__(
        self,
        model: PolicyModelContract,
        device: str | torch.device = "cpu",
        n_action_steps: int | None = None,
        num_inference_steps: int | None = None,
        noise_scale: float | None = None,
        record_attention: bool = False,
        cuda_graphs: bool = True,
    ):
        assert isinstance(model, PolicyModelContract), f"{type(model).__name__} does not satisfy the model contract"
        self.model = model.to(device).eval()
        if num_inference_steps is not None:
            model.set_inference_steps(num_inference_steps)
        if noise_scale is not None:
            model.set_noise_scale(noise_scale)
        self.device = torch.device(device)
        head = getattr(model, "head", None)
        if isinstance(head, DiffusionHead):
            head.cuda_graphs = cuda_graphs and self.device.type == "cuda"
        h = model.cfg.horizons
        self.n_obs_steps, self.horizon = h.n_obs_steps, h.horizon
        self.n_action_steps = n_action_steps or h.n_action_steps
        model.check_action_steps(self.n_action_steps)
        self.record_attention = record_attention
        self.context = None
        self.obs_keys = list(model.obs_keys())
        self.data_spec: DataSpec = model.data_spec()
        """What the model observes (keys, image size) and which action key it outputs."""

    # ------------------------------------------------------------ one rollout
    def reset(self, context: Mapping, seed: int = 0) -> None:
        """Start one rollout: validate and encode the task context once, clear history and queue."""
        self.reset_batch([context], [seed])

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The next action (A,) for the current observation (a dict of per-key arrays without time axis)."""
        return self.act_batch({k: np.asarray(obs[k])[None] for k in self.obs_keys})[0]

    # ------------------------------------------------- many rollouts in lockstep
    def reset_batch(self, contexts: Sequence[Mapping], seeds: Sequence[int]) -> None:
        """Start len(contexts) rollouts at once (they then step together); rollout i's noise is seeded by seeds[i]."""
        if len(contexts) != len(seeds) or not contexts:
            raise ValueError(f"need one seed per context, got {len(contexts)} contexts and {len(seeds)} seeds")
        batch = collate_contexts([self.model.validate_context(c) for c in contexts])
        with torch.no_grad():
            self.context = self.model.encode_context(to_torch(batch, self.device))
        self.generators = [torch.Generator(self.device).manual_seed(int(s)) for s in seeds]
        self.history: deque = deque(maxlen=self.data_spec.history_length)
        self.queue: deque = deque()
        self.attention_log: list[np.ndarray] = []  # per inference call: (B, n_chunks + 1)
        self.steps = 0

    def act_batch(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Next actions (B, A) for observations ``{key: (B, ...)}`` of the B rollouts started by reset_batch."""
        if self.context is None:
            raise RuntimeError("call reset(context) before act(obs)")
        obs = {k: np.asarray(obs[k]) for k in self.obs_keys}
        if not self.history:
            self.history.extend([obs] * (self.history.maxlen - 1))
        self.history.append(obs)
        if not self.queue:
            chunk = self.predict_chunk()
            start = self.n_obs_steps - 1
            self.queue.extend(np.swapaxes(chunk[:, start : start + self.n_action_steps], 0, 1))
        self.steps += 1
        return self.queue.popleft()

    def predict_chunk(self) -> np.ndarray:
        """Run the model on the current history: the full (B, T, A) action chunks."""
        read = history_at(self.history, self.data_spec.obs_offsets)
        stacked = {k: np.stack([o[k] for o in read], axis=1) for k in self.obs_keys}
        chunk, attention = predict_chunks(self.model, stacked, self.context, self.generators, self.record_attention)
        if attention is not None:
            self.attention_log.append(attention)
        return chunk


def history_at(history: Sequence, offsets: Sequence[int]) -> list:
    """The entries of a rollout's latest observations (`history`, oldest first) that a policy reads: those at step
    `offsets` (<= 0, :attr:`~bpp.data.spec.DataSpec.obs_offsets`) from the latest."""
    return [history[len(history) - 1 + o] for o in offsets]


def predict_chunks(
    model: PolicyModelContract,
    history: Mapping[str, np.ndarray],
    context,
    generators: Sequence[torch.Generator],
    return_attention: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """One inference call for B rollouts: observation histories ``{key: (B, To, ...)}`` and their encoded contexts
    -> action chunks (B, T, A) and, with `return_attention` where the model has it, the prompt attention
    (B, n_chunks + 1). Rollout i's noise comes from ``generators[i]`` alone, so its actions do not depend on the
    other rows (up to float sums, which differ with the batch size)."""
    device = next(model.parameters()).device
    shape = (model.cfg.horizons.horizon, model.action_dim)
    noise = torch.stack([torch.randn(shape, generator=g, device=device) for g in generators])
    out = model.predict_action(
        to_torch(history, device), context, noise=noise, generator=list(generators), return_attention=return_attention
    )
    attention = out["attention"].cpu().numpy() if return_attention and "attention" in out else None
    return out["action"].cpu().numpy(), attention
