"""Benchmarks and their environments, one folder each; each satisfies the contract of :mod:`bpp.core.contract` and is
found through :mod:`bpp.core.registry`.

Importing this package registers the environments of :data:`GYM_ENVS` with Gymnasium."""

import gymnasium as gym

GYM_ENVS: dict[str, str] = {
    "bpp/DrawAnything-v0": "bpp.benchmarks.draw.env:DrawEnv",
}
"""Gymnasium ids registered by ``import bpp.benchmarks`` (entry points are imported lazily, on ``gym.make``)."""

for _env_id, _entry_point in GYM_ENVS.items():
    if _env_id not in gym.registry:
        gym.register(_env_id, entry_point=_entry_point)
