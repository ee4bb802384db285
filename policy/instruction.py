"""An instruction's embedding as the policy reads it: the sentence's, then (config `text_goal`) its goal clause's.

Why: MiniLM mean-pools its tokens, so word order barely moves the sentence vector: "stack the red block on the
blue block" and "stack the blue block on the red block" are 0.997 alike (cosine), "put the red cube in the blue
bin" and its swap 0.972. Which block goes on which, or which bin the object goes in, is then a few thousandths of
the input. The words from the last "on/onto/in/into/inside/to" on ("on the blue block") name the goal alone.
Their embedding goes in a second slot after the sentence's, not added to it: a sum of the two roles' vectors is
symmetric in them again (measured: the swap stays 0.95-0.99 alike whatever is summed), while the slot holds
"on the blue block" and "on the red block" 0.81 alike. A command with no goal clause ("open the drawer") has
zeros there.

Torch-free (numpy only): the runtime's bundle loader composes the same way from its ONNX text encoder.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

# Prepositions that open a goal clause; the last one in the sentence wins ("on top of the blue block").
GOAL_WORDS = frozenset({"on", "onto", "in", "into", "inside", "to"})


def goal_clause(text: str) -> str | None:
    """The words from the last goal preposition on, or None where there is none (or nothing follows it)."""
    words = text.strip().split()
    for i in range(len(words) - 2, 0, -1):  # not the first word ("on the table, put ...") nor the last
        if words[i].lower().strip(",.;") in GOAL_WORDS:
            return " ".join(words[i:])
    return None


def embed_instructions(embed: Callable[[list[str]], np.ndarray], texts: Sequence[str], goal: bool) -> np.ndarray:
    """(N, D) float32 `embed(texts)`, or with `goal` (N, 2D): each sentence's embedding, then its goal clause's
    (zeros where it has none).

    embed: strings -> (M, D) sentence embeddings (MiniLM's unit vectors), called once."""
    texts = list(texts)
    if not goal:
        return np.asarray(embed(texts), np.float32)
    clauses = [goal_clause(t) for t in texts]
    extra = [c for c in clauses if c is not None]
    table = np.asarray(embed(texts + extra), np.float32)
    n, d = len(texts), table.shape[1]
    out = np.zeros((n, 2 * d), np.float32)
    out[:, :d] = table[:n]
    rows = [i for i, c in enumerate(clauses) if c is not None]
    out[rows, d:] = table[n:]
    return out
