"""Methods by name. Adding a method is a new folder under ``bpp/policies`` plus one line in :data:`METHODS`.

A method's package exports ``Config`` (a frozen dataclass: the model's whole configuration, saved in every
checkpoint), ``Model`` (tensor-only; ``Model(config, stats)``) and ``PRESETS`` (name -> Config, at least
``debug``, ``cpu`` and ``paper``). The model implements the contract used by :mod:`bpp.train` and
:class:`bpp.policies.agent.PolicyAgent`:

* ``context_kind``: ``"demo"``, ``"goal_image"`` or ``"instruction"`` (what ``reset(context)`` receives);
* ``data_spec() -> DataSpec``: what its training batches contain;
* ``forward(batch, generator) -> loss`` (``compute_loss``);
* ``obs_keys()``, ``validate_context(raw)``, ``encode_context(batch)``, ``predict_action(obs, context, ...)``;
* ``action_dim`` and ``cfg.horizons``.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

METHODS: dict[str, str] = {
    "bpp": "bpp.policies.bpp",
    "icrt": "bpp.policies.icrt",
    "goal_image": "bpp.policies.goal_image",
    "language": "bpp.policies.language",
}
"""Method name -> the package that implements it."""


@dataclass(frozen=True)
class Method:
    name: str
    config_cls: type
    model_cls: type
    presets: dict[str, Any]

    def preset(self, name: str):
        if name not in self.presets:
            raise ValueError(f"unknown {self.name} preset {name!r}; choose from {', '.join(self.presets)}")
        return self.presets[name]


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(METHODS)}")
    module = importlib.import_module(METHODS[name])
    return Method(name, module.Config, module.Model, module.PRESETS)
