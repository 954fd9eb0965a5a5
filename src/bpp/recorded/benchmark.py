"""The part of the benchmark contract (:class:`bpp.core.contract.Benchmark`) that recorded demonstrations share: their
stored camera frames, open-loop evaluation on held-out episodes scored by the action error (:mod:`bpp.recorded.replay`),
and pictures of a demonstration. A benchmark of recordings subclasses :class:`RecordedDemonstrations` and adds its name,
command, data and observation presets, and how its stores are made."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bpp.core.contract import Metric, RolloutResult
from bpp.data.frames import stored_frames
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.recorded import replay


class RecordedDemonstrations:
    """Demonstrations recorded in the world: train on them, evaluate open loop on held-out episodes."""

    derived_keys: Mapping[str, tuple[str, tuple[int, ...]]] = {}
    metric = Metric(
        "action error",
        lower_is_better=True,
        description=(
            "open loop on a recorded episode of the task other than the prompt: mean over its steps and action "
            "dimensions of |policy action - recorded action|, each dimension over half its range in the store"
        ),
    )
    max_steps = 1000
    """Replayed episodes are cut to this many steps."""
    task_sets: Mapping[str, str] = {}

    def frames(
        self, store: EpisodeStore, episode: int, key: str, size: int, last_only: bool = False, steps=None
    ) -> np.ndarray:
        """The camera frames recorded with the store (resized if another size is asked for)."""
        cameras = list(store.config.get("cameras", []))
        if key not in cameras:
            have = f"the cameras {', '.join(cameras)}" if cameras else "no cameras (train with --obs state)"
            raise UserError(f"{store.path} has {have}; got {key!r}")
        return stored_frames(store, episode, key, size, last_only, steps)

    def rollout_conditions(self, rng: np.random.Generator) -> dict:
        return {}

    def run_rollouts(self, agent, store, rollouts, max_steps, record_frames) -> list[RolloutResult]:
        return replay.run_rollouts(agent, store, rollouts, max_steps, record_frames, self.frames)

    def prompt_picture(self, store: EpisodeStore, episode: int, size: int = 256) -> np.ndarray:
        """The demonstration's last frame from its first camera, or a chart of its actions if it has no camera."""
        cameras = store.config.get("cameras", [])
        if cameras:
            return self.frames(store, episode, cameras[0], size, last_only=True)[0]
        actions = store.episode(episode, ["action"])["action"].astype(np.float64)
        return replay.action_chart(actions, title=f"episode {episode}", size=size)

    def describe_rollout(self, row: Mapping) -> str:
        return f"episode {row.get('replayed_episode', '?')}, open loop"
