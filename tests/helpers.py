"""Shortcuts the tests share: debug configs observing DrawAnything's state, and single DrawAnything rollouts."""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.core.prompting import run_prompted
from bpp.data.contexts import task_context
from bpp.data.spec import DataSpec
from bpp.policies.registry import get_method

DRAW_FRAMES = BENCHMARK.frames
"""DrawAnything's frame source (the ``frames`` a training dataset of a DrawAnything store renders its cameras with)."""

OPTIONAL_PARTS = {
    "libero": (("libero", "robosuite", "h5py"), "the libero extra: pip install -e '.[libero]'"),
    "studio": (("fastapi", "uvicorn", "httpx"), "the studio extra: pip install -e '.[studio]'"),
    "language": (("transformers",), "the language extra: pip install -e '.[language]'"),
    "serve": (("websockets", "msgpack"), "the serve extra: pip install -e '.[serve]'"),
    "lerobot": (("lerobot",), "make install-all builds .venv-lerobot: .venv-lerobot/bin/pytest tests/test_lerobot*.py"),
    "iphumi": (("cv2",), "the iphumi extra: pip install -e '.[iphumi]'"),
    "ray": (("ray",), "the ray extra: pip install -e '.[ray]'"),
    "openpi": ((), "the robot environment with openpi's client: make install-all (.venv-robot)"),
    "browser": (("playwright",), "playwright (the dev extra) and Debian's chromium (apt-get install chromium)"),
}
"""A marker naming an optional part -> the modules it needs and how to install them."""

ROBOT_PYTHON = Path(__file__).resolve().parents[1] / ".venv-robot" / "bin" / "python"
"""The robot-side environment `make install-all` builds: openpi's client (numpy < 2), bpp without torch."""

REQUIRE_ALL = bool(os.environ.get("BPP_REQUIRE_ALL"))
"""Set by `make test`, which installs every part and must run every test: a missing part fails instead of skipping."""


def _importable(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ImportError:  # an import hook that refuses it
        return False


def missing_parts(marker: str) -> list[str]:
    """What optional part `marker` needs and this environment lacks (module names, or ``chromium``)."""
    modules, _ = OPTIONAL_PARTS[marker]
    missing = [m for m in modules if not _importable(m)]
    if marker == "browser" and shutil.which("chromium") is None:
        missing.append("chromium")
    if marker == "openpi" and not ROBOT_PYTHON.is_file():
        missing.append(str(ROBOT_PYTHON))
    return missing


def import_optional(module: str, marker: str):
    """`module` of optional part `marker`, or skip the importing test file naming what to install. Under `make test`
    a missing part is an import error, so that it fails instead of being skipped."""
    if REQUIRE_ALL:
        return importlib.import_module(module)
    return pytest.importorskip(module, reason=f"needs {OPTIONAL_PARTS[marker][1]}")


KEYS = ["board_pose", "cursor_on_board", "agent_pos", "pen_down"]
"""What the ``canvas`` observation preset reads (the debug configs below observe it)."""


def config(method: str = "bpp", size: str = "debug", obs: str = "canvas", **overrides):
    """Method `method`'s size preset observing DrawAnything's observation preset `obs`, with field overrides."""
    return replace(get_method(method).config(size, obs, BENCHMARK), **overrides)


def prompt_from_store(store, episode: int, keys=KEYS, action_key: str = "action") -> dict:
    """A stored demonstration as a raw prompt ``{"obs": {key: (L, ...)}, "action": (L, A)}``."""
    return task_context(store, episode, DataSpec(lowdim_keys=tuple(keys), action_key=action_key))


def context_for(model, store, episode: int) -> dict:
    """The raw task context `model` expects, from demonstration `episode` (as evaluation builds it)."""
    return task_context(store, episode, model.data_spec(), BENCHMARK.frames)


@dataclass
class DrawResult:
    best_chamfer: float
    final_chamfer: float
    steps: int
    frames: list = field(repr=False)
    attention: np.ndarray | None = field(default=None, repr=False)


def rollout_batch(agent, store, episodes, angles, seeds, max_steps=400, record_frames=None, prompt_episodes=None):
    """Rollout i prompted with `prompt_episodes[i]` (default `episodes[i]`), scored on `episodes[i]`'s drawing, on a
    board at `angles[i]`, seeded by `seeds[i]`: the evaluation protocol's runner."""
    prompts = episodes if prompt_episodes is None else prompt_episodes
    if len(prompts) != len(episodes):
        raise ValueError(f"{len(prompts)} prompt episodes for {len(episodes)} rollouts")
    plan = [
        {"target_episode": t, "prompt_episode": p, "board_angle": a, "seed": s}
        for t, p, a, s in zip(episodes, prompts, angles, seeds, strict=True)
    ]
    record = record_frames or [False] * len(plan)
    results, attention = run_prompted(agent, BENCHMARK, store, plan, max_steps, record)
    return [
        DrawResult(r.score, r.extra["final_chamfer"], r.steps, r.frames, None if attention is None else attention[i])
        for i, r in enumerate(results)
    ]


def rollout(agent, store, episode, board_angle, seed=0, max_steps=400, record_frames=False) -> DrawResult:
    return rollout_batch(agent, store, [episode], [board_angle], [seed], max_steps, [record_frames])[0]


def _clip_tokenizer(folder: Path):
    """CLIP's byte-level BPE tokenizer over a vocabulary of single byte-characters (no merges): any text tokenizes."""
    from transformers import CLIPTokenizer
    from transformers.models.clip.tokenization_clip import bytes_to_unicode

    chars = list(bytes_to_unicode().values())
    tokens = [*chars, *(c + "</w>" for c in chars), "<|startoftext|>", "<|endoftext|>"]
    (folder / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    return CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"))


def _bert_tokenizer(folder: Path):
    """BERT's WordPiece tokenizer over letters, digits and punctuation (word starts and continuations)."""
    from transformers import BertTokenizer

    symbols = list("abcdefghijklmnopqrstuvwxyz0123456789")
    vocab = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", *symbols, *(f"##{s}" for s in symbols), *",.;:-'()"]
    (folder / "vocab.txt").write_text("\n".join(vocab) + "\n")
    return BertTokenizer(str(folder / "vocab.txt"))


def pretrained_text_folder(folder: Path, kind: str, seed: int = 0) -> Path:
    """A tiny random text encoder of `kind` and its tokenizer in `folder`, as transformers' save_pretrained writes
    them (a Hugging Face model folder, made offline): ``clip`` (a whole CLIP model, text and vision towers),
    ``clip_text_model`` (CLIP's text tower alone) or ``bert``."""
    import torch
    import transformers as tf

    folder.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    sizes = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2)
    if kind == "bert":
        tokenizer = _bert_tokenizer(folder)
        model = tf.BertModel(tf.BertConfig(vocab_size=len(tokenizer), max_position_embeddings=256, **sizes))
    else:
        tokenizer = _clip_tokenizer(folder)
        text = dict(
            vocab_size=len(tokenizer),
            max_position_embeddings=256,
            bos_token_id=tokenizer.bos_token_id,
            eos_token_id=tokenizer.eos_token_id,
            pad_token_id=tokenizer.pad_token_id,
            **sizes,
        )
        if kind == "clip":
            vision = dict(image_size=8, patch_size=4, num_channels=3, **sizes)
            model = tf.CLIPModel(tf.CLIPConfig(text_config=text, vision_config=vision, projection_dim=8))
        else:
            model = tf.CLIPTextModel(tf.CLIPTextConfig(**text))
    model.save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return folder


def obs_config(**fields):
    """An ObsConfig observing DrawAnything's ``canvas`` state keys, plus `fields` (e.g. a camera)."""
    from bpp.policies.config import ObsConfig

    canvas = BENCHMARK.observations["canvas"]
    return ObsConfig(**{"lowdim_keys": canvas.lowdim_keys, "proprio_keys": canvas.proprio_keys, **fields})


def assert_same_batches(a, b, where="batch"):
    """Nested dicts of arrays or tensors `a` and `b` are equal: the same keys, and every array the same exactly."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same_batches(a[k], b[k], f"{where}.{k}")
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)
