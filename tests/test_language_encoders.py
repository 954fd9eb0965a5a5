"""The Language baseline's text encoders: the offline default (a scratch encoder over UTF-8 bytes), and pretrained
encoders read only from a local Hugging Face folder (CLIP's text tower pooled at its end-of-text token, BERT-like
encoders mean-pooled), pinned by the SHA-256 of their weights. The folders here are tiny random models written with
transformers, so nothing is downloaded."""

import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from bpp.checkpoint import load_agent
from bpp.cli import main
from bpp.errors import UserError
from bpp.nn.text import ByteTokenizer, PretrainedTextEncoder, PretrainedTokenizer, masked_mean
from bpp.policies.language.config import PRESETS
from bpp.policies.language.model import LanguageModel
from bpp.train import TrainConfig, train
from bpp.utils import read_json
from helpers import config, pretrained_text_folder, rollout

KINDS = ["clip", "clip_text_model", "bert"]
"""The folders tested: a whole CLIP model (text and vision towers), CLIP's text tower alone, a BERT encoder."""


def pretrained(folder: Path, **fields):
    """The debug Language config fine-tuning the encoder in `folder`."""
    return replace(
        config("language"),
        text_encoder="pretrained",
        tokenizer="pretrained",
        pretrained_text_model=str(folder),
        **fields,
    )


def _train(store, run: Path, cfg, steps: int = 2, **fields):
    train_cfg = TrainConfig(
        data=store.path, out=run, method="language", steps=steps, batch_size=4, workers=0, warmup_steps=1, **fields
    )
    return train(train_cfg, cfg, progress=False)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_offline_default_is_a_scratch_encoder_over_bytes_and_the_paper_preset_asks_for_a_folder(
    described_store, tmp_path
):
    for size in ("debug", "cpu"):
        assert (PRESETS[size].text_encoder, PRESETS[size].tokenizer) == ("scratch", "bytes")
    model = LanguageModel(config("language", "cpu"), described_store.stats)
    assert isinstance(model.tokenizer, ByteTokenizer)
    # The paper preset fine-tunes a pretrained encoder, from a folder only the user can give: without one, training
    # stops before reading any data (the store does not exist), and leaves no run behind.
    paper = config("language", "paper", "paper")
    nowhere = TrainConfig(data=tmp_path / "none.zarr", out=tmp_path / "run", method="language", steps=1)
    for attempt in (lambda: train(nowhere, paper, progress=False), lambda: LanguageModel(paper, described_store.stats)):
        with pytest.raises(UserError, match="--model.pretrained-text-model PATH") as err:
            attempt()
        assert "openai/clip-vit-base-patch32" in str(err.value) and "any Hugging Face text encoder" in str(err.value)
    assert not (tmp_path / "run").exists()
    # The command line says so in one line, without a traceback.
    argv = ["train", "--method", "language", "--preset", "paper", "--data", str(described_store.path)]
    with pytest.raises(SystemExit) as exit:
        main([*argv, "--out", str(tmp_path / "run")])
    message = str(exit.value.code)
    assert message.startswith("bpp train: error: ") and "--model.pretrained-text-model PATH" in message
    assert "\n" not in message and not (tmp_path / "run").exists()


@pytest.mark.language
@pytest.mark.parametrize("kind", KINDS)
def test_a_pretrained_encoder_from_a_local_folder_fine_tunes_saves_loads_and_acts(
    described_store, tmp_path, monkeypatch, kind
):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    folder = pretrained_text_folder(tmp_path / kind, kind)
    cfg = pretrained(folder)
    run = tmp_path / "run"
    _train(described_store, run, cfg)
    agent = load_agent(run)
    model, weights = agent.model, folder / "model.safetensors"
    # The weights it started from are pinned, in the model config every checkpoint and the run record.
    pins = {"model.safetensors": _sha256(weights)}
    assert model.cfg == replace(cfg, pretrained_text_sha256=pins)
    assert read_json(run / "config.json")["model_config"]["pretrained_text_sha256"] == pins
    encoder, tokenizer = model.text_encoder, model.tokenizer
    assert isinstance(encoder, PretrainedTextEncoder) and isinstance(tokenizer, PretrainedTokenizer)
    assert encoder.dim == 16 and encoder.max_tokens == 256
    clip = kind != "bert"
    assert encoder.pooling == ("eos" if clip else "mean")
    assert type(encoder.model).__name__ == ("CLIPTextModel" if clip else "BertModel")
    if clip:  # the text tower only, also from a whole CLIP model
        assert all(k.startswith("text_model.") for k in encoder.model.state_dict())
    # Fine-tuned: the checkpoint's encoder differs from the folder's weights it started from.
    start = PretrainedTextEncoder(folder).state_dict()
    assert start.keys() == encoder.state_dict().keys()
    assert any(not torch.equal(v, start[k]) for k, v in encoder.state_dict().items())

    texts = ["draw a line", "draw a line, then lift the pen and move, then draw an oval"]
    ids, valid = tokenizer(texts, encoder.max_tokens)
    assert ids.shape == (2, tokenizer.num_tokens(texts[1]))
    with torch.no_grad():
        hidden = encoder.model(input_ids=ids, attention_mask=valid.long()).last_hidden_state
        pooled = encoder(ids, valid)
    if clip:  # CLIP's pooling: the end-of-text token's state (the last valid one; the padding repeats that token)
        ends = valid.sum(1) - 1
        assert (ids[torch.arange(2), ends] == tokenizer.tokenizer.eos_token_id).all()
        torch.testing.assert_close(pooled, hidden[torch.arange(2), ends])
    else:
        torch.testing.assert_close(pooled, masked_mean(hidden, valid))
    encoder.train()
    encoder(ids, valid).sum().backward()
    assert all(p.grad is not None for p in encoder.parameters())  # every weight fine-tunes (DDP needs it)

    result = rollout(agent, described_store, 1, 0.3, seed=0, max_steps=12)
    assert 0 < result.steps <= 12


@pytest.mark.language
def test_a_model_is_refused_when_its_pretrained_weights_changed(described_store, tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    folder = pretrained_text_folder(tmp_path / "clip", "clip_text_model")
    weights, kept = folder / "model.safetensors", tmp_path / "kept.safetensors"
    shutil.copyfile(weights, kept)
    trained_from = _sha256(weights)
    run = tmp_path / "run"
    _train(described_store, run, pretrained(folder))
    load_agent(run)
    _train(described_store, run, pretrained(folder), resume=True)  # the same weights: the run resumes (no steps left)

    pretrained_text_folder(tmp_path / "other", "clip_text_model", seed=1)
    shutil.copyfile(tmp_path / "other" / "model.safetensors", weights)  # other weights of the same shapes
    now = _sha256(weights)
    assert now != trained_from
    for attempt in (
        lambda: load_agent(run),  # evaluating, serving: loading a checkpoint
        lambda: _train(described_store, run, pretrained(folder), resume=True),  # resuming its run
        lambda: _train(
            described_store, tmp_path / "new", pretrained(folder, pretrained_text_sha256={weights.name: trained_from})
        ),
    ):
        with pytest.raises(UserError, match="not the weights this model was trained from") as err:
            attempt()
        assert str(weights) in str(err.value) and trained_from in str(err.value) and now in str(err.value)
    assert not (tmp_path / "new").exists()

    from transformers import CLIPTextModel

    weights.unlink()  # weights in another file (pytorch_model.bin) are refused too
    CLIPTextModel.from_pretrained(tmp_path / "other").save_pretrained(folder, safe_serialization=False)
    with pytest.raises(UserError, match="model.safetensors: not the weights .* none: the file is gone"):
        load_agent(run)

    shutil.copyfile(kept, weights)  # the original weights back: it loads again
    assert load_agent(run).model.cfg.pretrained_text_sha256 == {"model.safetensors": trained_from}


@pytest.mark.language
def test_a_clip_folder_whose_model_pools_another_token_than_its_tokenizer_ends_with_is_refused(
    described_store, tmp_path
):
    folder = pretrained_text_folder(tmp_path / "clip", "clip_text_model")
    settings = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**settings, "eos_token_id": 5}))
    with pytest.raises(UserError, match="the model pools token 5 .* they must agree"):
        LanguageModel(pretrained(folder), described_store.stats)
