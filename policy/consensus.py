"""Several draws of the sampler, one chunk: the medoid.

Why: between two runs of the same policy 16-28 % of stack's seeds flip (policy/EXPERIMENTS.md): which way an
episode goes is often one draw of the sampler, a chunk that lets go a few centimetres early or aims at the
edge of the block. K draws from the same observation cost one batched denoiser run; keeping the draw nearest
all the others (the medoid, least summed distance) drops the tails without averaging two modes into a chunk
no demonstration made, as a mean would.
"""

from __future__ import annotations

import numpy as np


def medoid(chunks: np.ndarray) -> int:
    """Index of the medoid of (K, T, D) chunks (Euclidean over all steps and dims; the first on ties)."""
    flat = np.asarray(chunks, np.float64).reshape(len(chunks), -1)
    if len(flat) <= 2:  # one draw, or two equally near each other
        return 0
    d = np.linalg.norm(flat[:, None] - flat[None], axis=-1)
    return int(np.argmin(d.sum(axis=1)))


def check_draws(n) -> int:
    """`n` as a draw count, or ValueError naming the allowed range."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_DRAWS:
        raise ValueError(f"draws {n!r}: expected an integer in [1, {MAX_DRAWS}] (1: one draw, no consensus)")
    return int(n)


MAX_DRAWS = 32
