"""Methods by name, and the contract every method's model implements.

Adding a method is a new folder under ``bpp/policies`` plus one line in :data:`METHODS`; packages outside bpp add
methods through the ``bpp.methods`` entry-point group (``name = "package.module"``). A method's package exports
``Config`` (a frozen dataclass: the model's whole configuration, saved in every checkpoint; a subclass of
:class:`~bpp.policies.config.PolicyConfig`, or of :class:`~bpp.policies.config.ContextDiffusionConfig` for a method
with the diffusion decoder, and with ``horizons``), ``PRESETS`` (size name -> Config, at least ``debug``, ``cpu`` and
``paper``) and ``MODEL``, the ``module:class`` of its model (tensor-only; ``Model(config, stats)``, satisfying
:class:`PolicyModelContract`). The package itself imports no torch, so that choosing a method and its configuration
(``bpp train --help``) is quick; the model's module is imported when a model is built (:attr:`Method.model_cls`). A
size preset observes nothing yet: :meth:`Method.config` combines it with a benchmark's observation preset (keys,
image size, action key).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from bpp.data.spec import ContextKind, DataSpec
from bpp.errors import UserError
from bpp.policies.config import with_observation

if TYPE_CHECKING:  # annotations only: the model's module imports torch
    import torch

METHODS: dict[str, str] = {
    "bpp": "bpp.policies.bpp",
    "icrt": "bpp.policies.icrt",
    "goal_image": "bpp.policies.goal_image",
    "language": "bpp.policies.language",
}
"""Method name -> the package that implements it."""


@runtime_checkable
class PolicyModelContract(Protocol):
    """What :func:`bpp.train.train` and :class:`bpp.policies.agent.PolicyAgent` use of a model besides its being a
    ``torch.nn.Module`` (parameters, state dict, ``to``, ``train``/``eval``; training wraps it in DDP).

    Shapes: B rollouts or samples; To = ``cfg.horizons.n_obs_steps``; T = ``cfg.horizons.horizon``; A = ``action_dim``.
    """

    method: str
    context_kind: ContextKind
    """What ``validate_context`` takes: ``demo``, ``goal_image`` or ``instruction`` (see bpp.data.contexts)."""
    cfg: Any
    """The method's Config; ``cfg.horizons`` gives To, T and the default Ta."""
    action_dim: int

    def data_spec(self) -> DataSpec:
        """What training batches and task contexts must contain."""
        ...

    def obs_keys(self) -> list[str]:
        """Per-step observation keys read at every step."""
        ...

    def forward(
        self, batch: Mapping, generator: torch.Generator | None = None, noise: Mapping | None = None
    ) -> torch.Tensor:
        """The training loss of a batch from :class:`bpp.data.prompt_dataset.PromptBatchDataset` (a scalar), with
        the random draws `noise` (from :meth:`draw_noise`; made from `generator` if None)."""
        ...

    def draw_noise(self, batch: Mapping, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """The random tensors one loss evaluation of `batch` uses (``{}`` for a loss that draws none)."""
        ...

    def validate_context(self, context: Mapping) -> dict:
        """A raw task context -> the same with batch dimension 1; ContextError naming what is wrong otherwise."""
        ...

    def encode_context(self, batch: Mapping) -> Any:
        """Batched contexts (tensors) -> the encoded context, once per rollout."""
        ...

    def predict_action(
        self,
        obs: Mapping[str, torch.Tensor],
        context: Any,
        noise: torch.Tensor | None = None,
        generator: torch.Generator | Sequence[torch.Generator] | None = None,
        return_attention: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Observations ``{key: (B, To, ...)}`` -> ``{"action": (B, T, A)}`` raw (plus ``"attention"`` (B, C) when
        asked and available). `noise` (B, T, A) and one generator per rollout make a rollout independent of its
        batch."""
        ...

    def set_inference_steps(self, steps: int) -> None:
        """Denoising steps per inference (ValueError if the model has no diffusion decoder)."""
        ...

    def check_action_steps(self, n_action_steps: int) -> None:
        """ValueError if executing `n_action_steps` actions per predicted chunk would be wrong for this model."""
        ...


@dataclass(frozen=True)
class Method:
    name: str
    config_cls: type
    model: str
    """``module:class`` of the model, imported by :attr:`model_cls`."""
    presets: dict[str, Any]

    @property
    def model_cls(self) -> type:
        """The model class (importing it imports torch)."""
        module, attr = self.model.split(":", 1)
        return getattr(importlib.import_module(module), attr)

    def preset(self, name: str):
        """A size preset (observing nothing yet: see :meth:`config`)."""
        if name not in self.presets:
            raise UserError(f"unknown {self.name} preset {name!r}; choose from {', '.join(self.presets)}")
        return self.presets[name]

    def config(self, size: str, obs: str | None, benchmark) -> Any:
        """Size preset `size` observing `benchmark`'s observation preset `obs` (None: the benchmark's default for
        that size)."""
        base = self.preset(size)
        name = obs or benchmark.default_observation(size)
        if name not in benchmark.observations:
            raise UserError(
                f"{benchmark.name} has no observation preset {name!r}; choose from {', '.join(benchmark.observations)}"
            )
        return with_observation(base, benchmark.observations[name])


def _plugins() -> dict[str, str]:
    """Methods other packages add: the ``bpp.methods`` entry points (name -> the package that implements it)."""
    return {ep.name: ep.value for ep in entry_points(group="bpp.methods")}


def method_names() -> list[str]:
    """The built-in methods, then those other packages add."""
    return [*METHODS, *sorted(set(_plugins()) - set(METHODS))]


def get_method(name: str) -> Method:
    """The method registered as `name` (built in, or added through the ``bpp.methods`` entry points)."""
    target = METHODS.get(name) or _plugins().get(name)
    if target is None:
        raise UserError(f"unknown method {name!r}; available: {', '.join(method_names())}")
    try:
        module = importlib.import_module(target)
    except ImportError as err:
        raise UserError(f"method {name!r}: cannot import its package {target!r} ({err})") from None
    missing = [attr for attr in ("Config", "MODEL", "PRESETS") if not hasattr(module, attr)]
    if missing:
        raise UserError(
            f"method {name!r}: its package {target!r} lacks {', '.join(missing)} (a method's package exports Config, "
            "PRESETS and MODEL)"
        )
    return Method(name, module.Config, module.MODEL, module.PRESETS)
