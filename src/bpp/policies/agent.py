"""The inference agent every evaluator and interface uses: numpy in, numpy out, one rollout at a time.

It owns what a rollout needs beyond the network: the task context encoded once at :meth:`reset` (for BPP, the
prompt's chunk embeddings), the observation history (To steps, the first observation repeated at the start),
the receding-horizon action queue (Ta of each predicted T-step chunk are executed), and a noise generator
seeded per rollout so that every method sees identical seeds.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from bpp.utils import to_torch


class PolicyAgent:
    """Wraps a tensor-only policy model for closed-loop control.

    Args:
        model: a policy model (``validate_context``, ``encode_context``, ``predict_action``).
        device: where to run the model.
        n_action_steps: actions executed per inference (default: the model's Ta).
        record_attention: keep the prompt attention of every inference in :attr:`attention_log`.
    """

    def __init__(
        self,
        model,
        device: str | torch.device = "cpu",
        n_action_steps: int | None = None,
        record_attention: bool = False,
    ):
        self.model = model.to(device).eval()
        self.device = torch.device(device)
        h = model.cfg.horizons
        self.n_obs_steps, self.horizon = h.n_obs_steps, h.horizon
        self.n_action_steps = n_action_steps or h.n_action_steps
        if not 1 <= self.n_action_steps <= self.horizon - self.n_obs_steps + 1:
            raise ValueError(f"n_action_steps must be in [1, {self.horizon - self.n_obs_steps + 1}]")
        self.record_attention = record_attention
        self.context = None
        self.generator = torch.Generator(self.device)

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "cpu", use_ema: bool = True, **kw) -> PolicyAgent:
        from bpp.checkpoint import load_policy

        return cls(load_policy(path, device, use_ema), device, **kw)

    def reset(self, context: Mapping, seed: int = 0) -> None:
        """Start a rollout: validate and encode the task context once, clear history and queue."""
        batch = self.model.validate_context(context)
        with torch.no_grad():
            self.context = self.model.encode_context(to_torch(batch, self.device))
        self.history: deque = deque(maxlen=self.n_obs_steps)
        self.queue: deque = deque()
        self.generator.manual_seed(seed)
        self.attention_log: list[np.ndarray] = []
        self.steps = 0

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The next action (A,) for the current observation (a dict of per-key arrays without time axis)."""
        if self.context is None:
            raise RuntimeError("call reset(context) before act(obs)")
        obs = {k: np.asarray(obs[k]) for k in self.model.context_keys()}
        if not self.history:
            self.history.extend([obs] * (self.n_obs_steps - 1))
        self.history.append(obs)
        if not self.queue:
            chunk = self.predict_chunk()
            start = self.n_obs_steps - 1
            self.queue.extend(chunk[start : start + self.n_action_steps])
        self.steps += 1
        return self.queue.popleft()

    def predict_chunk(self) -> np.ndarray:
        """Run the model on the current history: the full (T, A) action chunk."""
        stacked = {k: np.stack([o[k] for o in self.history])[None] for k in self.history[-1]}
        out = self.model.predict_action(
            to_torch(stacked, self.device),
            self.context,
            generator=self.generator,
            return_attention=self.record_attention,
        )
        if self.record_attention:
            self.attention_log.append(out["attention"][0].cpu().numpy())
        return out["action"][0].cpu().numpy()
