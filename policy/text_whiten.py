"""Whitening of the instruction embedding over the training instructions (config `text_whiten`, a ridge).

Why: MiniLM spends its 384 dimensions on what sentences are about, not on the word that picks the bin.
Over the demo data's 185 pick-and-place instructions, two that differ only in the bin are 0.12-0.16 apart
(median 1 - cosine 0.013), two that differ only in colour 0.50, only in shape 0.68, and two phrasings of the
same command 0.39: the slot the place depends on is the smallest variation in the input, smaller than the
phrasing, which the policy should ignore. A linear layer learns a direction in proportion to the input's
variance along it, so the bin is learned last and weakest. Whitening over the training instructions
(x - mean) @ (C + ridge I)^(-1/2), C their covariance, gives every direction the instructions vary along
about unit scale (the bin's distance grows to 2.4 against the colour's 4.2 at ridge 1e-3); the ridge keeps
directions they do not vary along (unseen phrasings) from being blown up.

The transform is fitted once where a model is made (`sudd pretrain` from nothing, or `sudd train` without a
warm start) and then travels with the weights: a warm start copies it (policy.warm_start.PRETRAINED) and the
exported obs_encoder graph contains it, so the runtime feeds the raw embedding as before. Its values are
rounded to float16 when fitted, so the bundle's fp16 weight storage (policy.fp16) stores them exactly.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def fit_whitening(embeddings: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) embeddings of distinct instructions -> mean (D,) and the symmetric (D, D) matrix
    (C + ridge I)^(-1/2), C their covariance."""
    x = np.asarray(embeddings, np.float64)
    if x.ndim != 2 or len(x) < 2:
        raise ValueError(f"text whitening needs at least 2 distinct instructions as an (N, D) array, got {x.shape}; "
                         "for data with one instruction leave text_whiten at 0")
    if ridge <= 0:
        raise ValueError(f"text whitening ridge must be > 0, got {ridge}")
    mean = x.mean(axis=0)
    cov = (x - mean).T @ (x - mean) / len(x)
    vals, vecs = np.linalg.eigh(cov)
    matrix = (vecs / np.sqrt(np.clip(vals, 0.0, None) + ridge)) @ vecs.T
    return mean.astype(np.float32), matrix.astype(np.float32)


class TextWhitening(nn.Module):
    """(B, D) raw embedding -> (B, D) whitened; the identity until `fit_` is called."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("matrix", torch.eye(dim))
        self.register_buffer("fitted", torch.zeros(()))

    @property
    def is_fitted(self) -> bool:
        return bool(self.fitted.item())

    def fit_(self, embeddings: np.ndarray, ridge: float) -> None:
        mean, matrix = fit_whitening(embeddings, ridge)
        self.mean.copy_(torch.from_numpy(mean).half().float())
        self.matrix.copy_(torch.from_numpy(matrix).half().float())
        self.fitted.fill_(1.0)

    def forward(self, text: torch.Tensor) -> torch.Tensor:
        return (text - self.mean) @ self.matrix


def prepare(model: nn.Module, dataset, warm: dict | None) -> dict | None:
    """Before a new run's first step: fit the whitening of a model made from nothing on the dataset's distinct
    instructions; a warm-started one must have brought its own (the encoders it copied read that whitening).
    Returns what was done, for the run's dataset.json; None when `text_whiten` is off."""
    whiten = model.obs_encoder.text_whiten
    if whiten is None:
        return None
    if warm is not None:
        if not whiten.is_fitted:
            raise ValueError(f"text_whiten is on but the warm-start source {warm['source']} was trained without it "
                             "(its encoders read the raw embedding): pretrain with the same --set text_whiten, "
                             "or leave text_whiten at 0")
        return {"ridge": model.cfg.text_whiten, "from": warm["source"]}
    rows = sorted({dataset.text_row[t] for t in dataset.instructions})
    whiten.fit_(dataset.text_table[rows].numpy(), model.cfg.text_whiten)
    return {"ridge": model.cfg.text_whiten, "instructions": len(rows)}
