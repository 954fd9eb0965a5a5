"""Instruction encoders: tokenizers and text transformers that turn a batch of texts into one embedding per text.

Two tokenizers (a UTF-8 byte tokenizer that needs no vocabulary, and the tokenizer that comes with a pretrained
model) and two encoders (a pre-norm transformer trained from scratch, and a pretrained Hugging Face encoder
fine-tuned with the policy). Every combination returns ``(ids, valid)`` / ``(B, D)`` the same way.

Pretrained files are only ever read from a local folder the user supplies; nothing is downloaded, and no package
ships them. The makers of the text encoders worth fine-tuning (OpenAI for CLIP, which the paper fine-tunes; the
sentence-transformers authors for MiniLM) publish their weights in their own Hugging Face repositories, not on a
package registry, so bpp cannot depend on them: a user copies one once (``hf download openai/clip-vit-base-patch32
--local-dir ...``) and passes the folder. transformers, by Hugging Face (the ``language`` extra), reads it. The
weights a model was trained from are pinned by their SHA-256 (:func:`weights_sha256`, :func:`check_weights`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from bpp.errors import UserError, require_extra

PAPER_TEXT_MODEL = "openai/clip-vit-base-patch32"
"""A CLIP text tower to fine-tune: ViT-B/32's (OpenAI; on the Hugging Face Hub). The paper fine-tunes CLIP's
text encoder without naming the variant."""

NO_PRETRAINED_MODEL = (
    "the pretrained text encoder reads a local Hugging Face model folder, and none was given: pass "
    f"--model.pretrained-text-model PATH, e.g. a local copy of {PAPER_TEXT_MODEL} (CLIP, which the paper "
    f"fine-tunes; made once where there is a network: hf download {PAPER_TEXT_MODEL} --local-dir PATH) or of any "
    "Hugging Face text encoder (config.json, weights, tokenizer files); nothing is downloaded at run time. Or "
    "train an encoder from scratch: --model.text-encoder scratch --model.tokenizer bytes"
)
"""What a model that needs a pretrained folder says when none is given."""

CLIP_TYPES = ("clip", "clip_text_model")
"""``model_type``s of config.json whose text tower is loaded as CLIP's (:class:`PretrainedTextEncoder`): the whole
CLIP model (text and vision towers) and its text tower alone."""

WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
"""The weight files transformers reads from a folder, in its order of preference (each may be split into shards
listed in ``<name>.index.json``)."""


def pretrained_text_dir(path: str = "") -> Path:
    """The local folder of a pretrained text encoder: `path`, which must hold a Hugging Face model (config.json).
    None given: a UserError that says what to pass (nothing is downloaded)."""
    if not path:
        raise UserError(NO_PRETRAINED_MODEL)
    folder = Path(path).expanduser()
    if not (folder / "config.json").is_file():
        raise UserError(
            f"{folder}: not a pretrained text encoder (expected a local Hugging Face model folder with config.json, "
            "weights and tokenizer files)"
        )
    return folder


def model_type(folder: Path) -> str:
    """The ``model_type`` that `folder`'s config.json names ("" if none)."""
    try:
        config = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError) as err:
        raise UserError(f"{folder / 'config.json'}: unreadable ({err})") from None
    return str(config.get("model_type", "")) if isinstance(config, dict) else ""


def weight_files(folder: Path) -> list[Path]:
    """The weight files transformers loads from `folder`: model.safetensors, else pytorch_model.bin (or the shards
    their ``.index.json`` lists)."""
    for name in WEIGHT_FILES:
        if (folder / name).is_file():
            return [folder / name]
        index = folder / f"{name}.index.json"
        if index.is_file():
            try:
                shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
                raise UserError(f"{index}: unreadable shard index ({type(err).__name__}: {err})") from None
            return [folder / shard for shard in shards]
    raise UserError(f"{folder}: no weights (expected {' or '.join(WEIGHT_FILES)}, or their shards)")


_DIGESTS: dict[tuple[str, int, int], str] = {}
"""SHA-256 by (resolved path, size, modification time): a folder's weights are hashed once per process."""


def file_sha256(path: Path) -> str:
    """The SHA-256 of file `path` (hex), read in 16 MiB blocks; remembered while its size and time are unchanged."""
    resolved = path.resolve()
    stat = resolved.stat()
    key = (str(resolved), stat.st_size, stat.st_mtime_ns)
    if key not in _DIGESTS:
        digest = hashlib.sha256()
        with open(resolved, "rb") as f:
            while block := f.read(16 << 20):
                digest.update(block)
        _DIGESTS[key] = digest.hexdigest()
    return _DIGESTS[key]


def weights_sha256(folder: Path) -> dict[str, str]:
    """The SHA-256 of each weight file of `folder` (:func:`weight_files`), by its name in the folder."""
    return {os.path.relpath(path, folder): file_sha256(path) for path in weight_files(folder)}


def check_weights(folder: Path, recorded: Mapping[str, str]) -> None:
    """Refuse `folder` if its weight files are not those `recorded` (name -> SHA-256, as :func:`weights_sha256`
    gives): a UserError naming the first file that differs and both digests."""
    now = weights_sha256(folder)
    for name in sorted(set(recorded) | set(now)):
        if recorded.get(name) != now.get(name):
            raise UserError(
                f"{folder / name}: not the weights this model was trained from (SHA-256 "
                f"{recorded.get(name, 'none: the file was not there')} recorded, "
                f"{now.get(name, 'none: the file is gone')} now): put back the weights it was trained from"
            )


def masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, L, D) tokens and their (B, L) valid mask -> (B, D): the mean of the valid tokens."""
    weights = valid.unsqueeze(-1).to(x.dtype)
    return (x * weights).sum(1) / weights.sum(1).clamp_min(1.0)


def padded_tokens(longest: int, multiple: int, max_tokens: int, unit: str = "tokens") -> int:
    """A batch's token length: its longest text's `longest` tokens (`unit`) rounded up to a multiple of `multiple`,
    at most `max_tokens`; a longer text is refused."""
    if longest > max_tokens:
        raise UserError(f"a text of {longest} tokens ({unit}) exceeds the encoder's {max_tokens}")
    return min(-(-longest // multiple) * multiple, max_tokens)


class ByteTokenizer:
    """Text -> token ids: [BOS] + the text's UTF-8 bytes (+3) + [EOS], padded with [PAD] to the longest.

    Bytes need no vocabulary to learn or to store: any text tokenizes.
    """

    PAD, BOS, EOS = 0, 1, 2
    OFFSET = 3
    vocab_size = 256 + OFFSET
    unit = "UTF-8 bytes + 2"

    @staticmethod
    def num_tokens(text: str) -> int:
        return len(text.encode("utf-8")) + 2

    def __call__(self, texts: Sequence[str], max_tokens: int, multiple: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids (B, L) long and their valid mask (B, L) bool, L = the longest text's tokens, rounded up to a
        `multiple` (at most `max_tokens`)."""
        encoded = [[self.BOS, *(b + self.OFFSET for b in t.encode("utf-8")), self.EOS] for t in texts]
        length = padded_tokens(max(len(e) for e in encoded), multiple, max_tokens, self.unit)
        ids = torch.full((len(encoded), length), self.PAD, dtype=torch.long)
        for i, e in enumerate(encoded):
            ids[i, : len(e)] = torch.tensor(e)
        return ids, ids != self.PAD


class PretrainedTokenizer:
    """The tokenizer of a pretrained model folder (AutoTokenizer: CLIP's byte-level BPE, BERT's WordPiece, ...), with
    the same interface as the bytes'."""

    def __init__(self, folder: Path):
        AutoTokenizer = require_extra("transformers", "language").AutoTokenizer

        self.tokenizer = AutoTokenizer.from_pretrained(folder, local_files_only=True)
        if self.tokenizer.pad_token is None:  # GPT-style tokenizers: padding is masked, any token will do
            if self.tokenizer.eos_token is None:
                raise UserError(f"{folder}: the tokenizer has neither a padding nor an end-of-text token")
            self.tokenizer.pad_token = self.tokenizer.eos_token
        self.vocab_size = len(self.tokenizer)
        self.unit = f"{type(self.tokenizer).__name__} tokens incl. special"

    def num_tokens(self, text: str) -> int:
        return len(self.tokenizer(text)["input_ids"])

    def __call__(self, texts: Sequence[str], max_tokens: int, multiple: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids (B, L) long and their valid mask (B, L) bool, L = the longest text's tokens, rounded up to a
        `multiple` (at most `max_tokens`)."""
        batch = self.tokenizer(list(texts), padding=True, return_tensors="pt")
        longest = batch["input_ids"].shape[1]
        pad = padded_tokens(longest, multiple, max_tokens, self.unit) - longest
        ids = F.pad(batch["input_ids"], (0, pad), value=self.tokenizer.pad_token_id)
        return ids, F.pad(batch["attention_mask"], (0, pad)).bool()


class TextTransformer(nn.Module):
    """Token ids (B, L) + valid mask (B, L) -> one text embedding (B, D): the mean of the valid output tokens.

    A pre-norm transformer trained from scratch with the policy.
    """

    def __init__(self, vocab_size: int, dim: int, layers: int, heads: int, mlp_dim: int, max_tokens: int, dropout=0.0):
        super().__init__()
        self.dim, self.max_tokens = dim, max_tokens
        self.embed = nn.Embedding(vocab_size, dim)
        self.pos = nn.Parameter(torch.randn(max_tokens, dim) * 0.02)
        layer = nn.TransformerEncoderLayer(
            dim, heads, mlp_dim, dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(dim)

    def forward(self, ids: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        x = self.embed(ids) + self.pos[: ids.shape[1]]
        return masked_mean(self.norm(self.encoder(x, src_key_padding_mask=~valid)), valid)


class PretrainedTextEncoder(nn.Module):
    """A pretrained Hugging Face text encoder from a local folder, pooled to one embedding per text; its weights train
    with the policy (fine-tuning). Token ids (B, L) -> (B, D).

    A CLIP folder (config.json's ``model_type`` ``clip``, the whole model, or ``clip_text_model``) loads only the text
    tower (transformers' ``CLIPTextModel``; the whole model's vision tower and projections are not loaded), pooled as
    CLIP pools: the hidden state of the end-of-text token after the final layer norm (its ``pooler_output``). Any
    other folder loads with ``AutoModel``, pooled as sentence-transformers pools BERT-like encoders: the mean of the
    valid tokens' last hidden states.
    """

    def __init__(self, folder: Path):
        super().__init__()
        transformers = require_extra("transformers", "language")
        self.folder = folder
        self.pooling = "eos" if model_type(folder) in CLIP_TYPES else "mean"
        with _quiet_transformers():
            if self.pooling == "eos":
                self.model = transformers.CLIPTextModel.from_pretrained(folder, local_files_only=True)
            else:
                try:  # BERT-family models carry a [CLS] pooler that mean pooling leaves unused (DDP requires every
                    # parameter to take part), so it is not built
                    self.model = transformers.AutoModel.from_pretrained(
                        folder, local_files_only=True, add_pooling_layer=False
                    )
                except TypeError:  # architectures without that option
                    self.model = transformers.AutoModel.from_pretrained(folder, local_files_only=True)
        config = self.model.config
        self.dim = config.hidden_size
        self.max_tokens = config.max_position_embeddings

    def check_tokenizer(self, tokenizer: PretrainedTokenizer) -> None:
        """Refuse a tokenizer whose end-of-text token is not the one CLIP pooling picks (config.json's
        ``eos_token_id``; 2, the value of older CLIP configs, means the largest id, which is CLIP's end token)."""
        pooled, ends = self.model.config.eos_token_id, tokenizer.tokenizer.eos_token_id
        if self.pooling == "eos" and pooled != 2 and pooled != ends:
            raise UserError(
                f"{self.folder}: the tokenizer ends a text with token {ends}, but the model pools token {pooled} "
                "(config.json's eos_token_id); they must agree"
            )

    def forward(self, ids: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        out = self.model(input_ids=ids, attention_mask=valid.long())
        return out.pooler_output if self.pooling == "eos" else masked_mean(out.last_hidden_state, valid)


@contextlib.contextmanager
def _quiet_transformers() -> Iterator[None]:
    """transformers without its reports of weights left out (a whole CLIP model's vision tower, a BERT pooler) and
    its per-load progress bar: noise here."""
    from transformers.utils import logging as hf_logging  # the language extra; the caller has checked it

    verbosity, bars = hf_logging.get_verbosity(), hf_logging.is_progress_bar_enabled()
    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        hf_logging.set_verbosity(verbosity)
        if bars:
            hf_logging.enable_progress_bar()
