"""The configuration parts every method shares: the observation encoders, the diffusion action decoder and the
horizons, with the range rules they are validated by; the size-preset parts several methods use; and
:func:`with_observation`, which points a size preset at a benchmark's observation preset.

Plain dataclasses, no torch: a config is built, validated and saved without loading a model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from bpp.errors import UserError
from bpp.utils import check_fields


def group_normable(channels: int) -> bool:
    """Whether the image encoder's GroupNorm (channels // 16 groups, at least 1) divides `channels`."""
    return channels >= 1 and channels % max(1, channels // 16) == 0


IMAGE_WIDTHS_RULE = (
    "channel counts >= 1, each below 16 or divisible by its GroupNorm groups (width // 16), e.g. 32, 64, 128"
)
_DOWN = "channel counts, each a multiple of 8 (the decoder's GroupNorm has 8 groups)"
BETA_SCHEDULES = ("linear", "scaled_linear", "squaredcos_cap_v2")
PREDICTION_TYPES = ("epsilon", "sample", "v_prediction")


def transformer_rules(cfg) -> tuple[tuple[str, bool, str], ...]:
    """Range rules for the transformer fields a model config shares: dim, layers, heads, mlp_dim, dropout."""
    return (
        ("dim", cfg.dim >= 1, ">= 1"),
        ("layers", cfg.layers >= 1, ">= 1"),
        ("heads", cfg.heads >= 1 and cfg.dim % cfg.heads == 0, f"a divisor of dim ({cfg.dim})"),
        ("mlp_dim", cfg.mlp_dim >= 1, ">= 1"),
        ("dropout", 0.0 <= cfg.dropout < 1.0, "in [0, 1)"),
    )


@dataclass(frozen=True)
class ObsConfig:
    """Which observation entries a policy sees, and how they are encoded.

    The keys and the image size come from a benchmark's observation preset (:func:`with_observation`); a method's
    size preset (``debug``, ``cpu``, ``paper``) sets the encoders' sizes.
    """

    image_keys: tuple[str, ...] = ()
    """Camera keys, (H, W, 3) uint8 images (empty: state-only)."""
    lowdim_keys: tuple[str, ...] = ()
    """Low-dimensional observation keys other than proprioception (one entry each)."""
    proprio_keys: tuple[str, ...] = ()
    """Proprioception keys (one entry each); the prompt can include or drop them as a group."""
    image_size: int = 96
    image_features: int = 256
    image_widths: tuple[int, ...] = (32, 64, 128, 256)
    image_blocks: tuple[int, ...] = (1, 1, 1, 1)
    image_stem: str = "conv5"
    """resnet: ResNet's 7x7 stride-2 convolution and max-pool (the paper's ResNet-18); conv5: one 5x5 stride-2
    convolution, twice the resolution after the stem, for small images (see :class:`bpp.nn.vision.ResNetGN`)."""
    image_pool_grid: int = 1
    """1: the encoder averages its last feature map over the image (what is in view, not where); g > 1: over a g x g
    grid, flattened, so that the features keep where things are."""
    lowdim_fourier_octaves: int = 0
    """0: low-dimensional entries are their normalised values; k > 0: Fourier features over k octaves and an MLP
    to ``lowdim_features`` (a nonlinear embedding, so that attention can match nearby states; see bpp.nn.lowdim)."""
    lowdim_features: int = 64

    def __post_init__(self):
        widths, blocks = self.image_widths, self.image_blocks
        check_fields(
            self,
            ("image_size", 8 <= self.image_size <= 1024, "in [8, 1024] px"),
            ("image_features", self.image_features >= 1, ">= 1"),
            ("image_widths", len(widths) >= 1 and all(group_normable(w) for w in widths), IMAGE_WIDTHS_RULE),
            ("image_blocks", len(blocks) == len(widths) and all(b >= 1 for b in blocks), "one count >= 1 per width"),
            ("image_stem", self.image_stem in ("resnet", "conv5"), "'resnet' or 'conv5'"),
            ("image_pool_grid", 1 <= self.image_pool_grid <= 16, "in [1, 16]"),
            ("lowdim_fourier_octaves", 0 <= self.lowdim_fourier_octaves <= 16, "in [0, 16]"),
            ("lowdim_features", self.lowdim_features >= 1, ">= 1"),
        )

    @property
    def entries(self) -> list[str]:
        """Observation entries in token order (one token per entry per history step): cameras, lowdim, proprio."""
        return [*self.image_keys, *self.lowdim_keys, *self.proprio_keys]


@dataclass(frozen=True)
class DiffusionConfig:
    """The action decoder: a FiLM 1D U-Net trained with DDPM and sampled with DDIM (diffusers schedulers)."""

    down_dims: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 5
    step_embed_dim: int = 64
    num_train_steps: int = 100
    """K: diffusion steps at training."""
    num_inference_steps: int = 16
    """Denoising steps at inference (DDIM)."""
    beta_schedule: str = "squaredcos_cap_v2"
    sampler: str = "ddim"
    """ddim or ddpm."""
    prediction_type: str = "epsilon"
    """What the U-Net predicts from a noised chunk: ``epsilon`` (the noise, Diffusion Policy's and the paper's
    choice), ``sample`` (the clean chunk) or ``v_prediction`` (√ᾱ·ε - √(1-ᾱ)·x₀); the loss is the mean squared
    error of that prediction, and the sampler reads the network's output as the same quantity."""
    noise_scale: float = 1.0
    """The sampler starts from its noise times this (inference only): 1 draws from the distribution the decoder
    learned; below 1 draws nearer the chunk it finds most likely, and 0 always returns that one chunk (DDIM)."""

    def __post_init__(self):
        check_fields(
            self,
            ("down_dims", len(self.down_dims) >= 1 and all(d >= 8 and d % 8 == 0 for d in self.down_dims), _DOWN),
            ("kernel_size", self.kernel_size >= 1 and self.kernel_size % 2 == 1, "odd and >= 1"),
            ("step_embed_dim", self.step_embed_dim >= 2 and self.step_embed_dim % 2 == 0, "even and >= 2"),
            ("num_train_steps", 1 <= self.num_train_steps <= 10_000, "in [1, 10000]"),
            ("num_inference_steps", 1 <= self.num_inference_steps <= self.num_train_steps, "in [1, num_train_steps]"),
            ("beta_schedule", self.beta_schedule in BETA_SCHEDULES, f"one of {BETA_SCHEDULES}"),
            ("sampler", self.sampler in ("ddim", "ddpm"), "'ddim' or 'ddpm'"),
            ("prediction_type", self.prediction_type in PREDICTION_TYPES, f"one of {PREDICTION_TYPES}"),
            ("noise_scale", 0.0 <= self.noise_scale <= 2.0, "in [0, 2]"),
        )

    def check_horizon(self, horizon: int) -> None:
        """The U-Net halves the time axis between levels: refuse a horizon it cannot halve that often."""
        factor = 2 ** (len(self.down_dims) - 1)
        if horizon % factor:
            raise UserError(
                f"horizons.horizon {horizon} must be a multiple of {factor} for a decoder with "
                f"{len(self.down_dims)} levels (diffusion.down_dims {self.down_dims})"
            )


@dataclass(frozen=True)
class Horizons:
    """To (n_obs_steps), T (horizon) and Ta (n_action_steps); the executed actions start at index To - 1."""

    n_obs_steps: int = 2
    horizon: int = 16
    n_action_steps: int = 12

    def __post_init__(self):
        check_fields(
            self,
            ("n_obs_steps", self.n_obs_steps >= 1, ">= 1"),
            ("horizon", self.n_obs_steps <= self.horizon <= 1024, "in [n_obs_steps, 1024]"),
        )
        if not 1 <= self.n_action_steps <= self.horizon - self.n_obs_steps + 1:
            raise UserError(
                f"need 1 <= n_action_steps <= horizon - n_obs_steps + 1, got Ta={self.n_action_steps}, "
                f"T={self.horizon}, To={self.n_obs_steps}"
            )


@dataclass(frozen=True)
class PolicyConfig:
    """The fields every method's config has (the base of each method's ``Config``, which adds its own).

    A method's config is everything that defines its model; every run and checkpoint saves it as JSON
    (:func:`bpp.utils.to_dict`) and rebuilds it from there (:func:`bpp.utils.from_dict`), so a field's name is part of
    the saved format.
    """

    obs: ObsConfig = field(default_factory=ObsConfig)
    action_key: str = "action"
    """The per-step key the policy predicts (set by a benchmark's observation preset)."""
    action_relative_to: str = ""
    """"": absolute actions (the paper). An observed position key, in the frame of the actions' first dims: actions
    are learned and predicted as offsets from its value at the current step (see
    :meth:`bpp.policies.model.PolicyModel.normalize_actions`; where it was tried it did not help: BENCHMARKS.md)."""

    def pinned(self, recorded: Mapping | None = None):
        """The config a training run starts from and records, called before the run reads any data: a method whose
        model reads files of the user's besides the config (Language's pretrained text encoder) checks here that they
        are there and records their digests, which the model checks whenever it is built. `recorded`: the model
        config (JSON) of the run being resumed, whose digests are checked rather than new ones taken. The base
        reads no such files: the config itself."""
        return self


@dataclass(frozen=True)
class ContextDiffusionConfig(PolicyConfig):
    """The fields of a method with the diffusion action decoder (:class:`bpp.policies.model.ContextDiffusionPolicy`):
    the horizons and the decoder, which must be able to halve the horizon at each of its levels."""

    horizons: Horizons = field(default_factory=Horizons)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)

    def __post_init__(self):
        self.diffusion.check_horizon(self.horizons.horizon)


# Size-preset parts that several methods share (each method's config.py names its own size presets; the keys come
# from a benchmark's observation preset, see with_observation).
DEBUG_DIFFUSION = DiffusionConfig(down_dims=(32, 64), step_embed_dim=16, num_train_steps=20, num_inference_steps=4)
"""The tiny action decoder of the ``debug`` presets."""
DEBUG_OBS = ObsConfig(image_features=16, image_widths=(8, 16), image_blocks=(1, 1))
"""The ``debug`` presets' encoders: normalised state, a tiny image encoder."""
CPU_OBS = ObsConfig(lowdim_fourier_octaves=6, image_features=128, image_widths=(16, 32, 64, 128))
"""The ``cpu`` presets' encoders: Fourier-feature embeddings of every low-dimensional entry (see bpp.nn.lowdim for
why), a small ResNet-GN for cameras (64x64 images on a CPU)."""
PAPER_OBS = ObsConfig(
    image_features=512, image_widths=(64, 128, 256, 512), image_blocks=(2, 2, 2, 2), image_stem="resnet"
)
"""The paper's encoders: ResNet-18 (GroupNorm, ResNet's stem) for cameras."""
PAPER_DIFFUSION = DiffusionConfig(down_dims=(256, 512, 1024), step_embed_dim=128)
"""The paper's action decoder: U-Net [256, 512, 1024], kernel 5, step embedding 128."""


def with_observation(cfg, preset):
    """A method config (any with ``obs`` and ``action_key``) that observes and acts as a benchmark's observation
    preset says (:class:`bpp.data.spec.ObservationPreset`): its keys, image size and action key. The encoders keep
    the size preset's widths. A config class may define ``observation_overrides(obs, preset) -> dict`` for fields
    that follow the observations (e.g. Goal-Image's goal camera, and its size when it shares the camera encoder)."""
    obs = replace(
        cfg.obs,
        image_keys=tuple(preset.image_keys),
        lowdim_keys=tuple(preset.lowdim_keys),
        proprio_keys=tuple(preset.proprio_keys),
        image_size=preset.image_size,
    )
    fields = {"obs": obs, "action_key": preset.action_key}
    hook = getattr(cfg, "observation_overrides", None)
    if hook is not None:
        fields.update(hook(obs, preset))
    return replace(cfg, **fields)
