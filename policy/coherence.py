"""Backward coherence: of K chunks sampled for one observation, run the one that agrees best with the chunk that ran
just before it.

Why: the runtime replans at every policy tick (`replan_every` 1) from fresh noise, and a diffusion policy's chunks for
nearly the same observation can come from different modes of what it learned: reach left of the object or right of
it, let go now or a moment later. Drawn independently at every tick, the arm can switch between them from one tenth of
a second to the next and commit to neither. On drawer_stow seed 100500, of four chunks drawn at a tick the two furthest
apart lie 1.9 cm apart over their rows (median over the ticks; 3.2 cm at the 90th percentile), and at one tick in four
two of them disagree by more than half the gripper's range. Liu et al. ("Bidirectional Decoding", ICLR 2025) pick,
among several samples, the one closest to the previous decision over the steps both cover ("backward coherence");
their "forward contrast" needs a second, weaker policy, which a bundle does not carry.

How: `Bundle.act(samples=K)` denoises K noises in one batch (the observation is encoded once). Each candidate's
executed rows are compared with the rows of the chunk picked last that fall at the same times: a chunk made s ticks
later is ahead by s rows, so its rows 0..n-1-s against the earlier one's s..n-1. The distance weighs the position
in centimetres, the 6-D rotation and the gripper request each times ten (0.1 of either counts as 1 cm), row i by
DECAY**i: the near future matters most, the far one will be replanned. With nothing to compare with (the first
tick, after the look or a retreat moved the arm, a gap longer than the chunk) the first sample runs. K = 1 draws and
runs exactly what the plain sampler does.

Torch-free (numpy only): `sudd eval` and the runtime's policy node use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import GRIPPER_COLUMN

MAX_SAMPLES = 32
DECAY = 0.9  # weight of each row after the first in the distance
POS_SCALE = 100.0  # metres -> centimetres
ROT_GRIP_SCALE = 10.0  # 0.1 of a 6-D rotation entry or of the gripper request counts as 1 cm


def check_samples(k) -> int:
    """The number of chunks to sample per tick: an integer in 1..MAX_SAMPLES; ValueError otherwise."""
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_SAMPLES:
        raise ValueError(f"coherence samples = {k!r}: expected an integer in 1..{MAX_SAMPLES} (1: no choice, the "
                         "plain sampler; `sudd bench policy` times 4 and 8)")
    return k


def chunk_distance(candidates: np.ndarray, earlier: np.ndarray, shift: int) -> np.ndarray:
    """(K,) weighted distance of each candidate (K, n, Da) from the `earlier` chunk (n, Da) made `shift` rows
    (policy ticks) before it, over the rows both cover (module doc); zeros where they cover none."""
    c, e = np.asarray(candidates, np.float64), np.asarray(earlier, np.float64)
    overlap = min(c.shape[1], e.shape[0] - shift)
    if shift < 0 or overlap <= 0:
        return np.zeros(len(c))
    d = c[:, :overlap] - e[shift:shift + overlap][None]
    per_row = (POS_SCALE * np.linalg.norm(d[..., :3], axis=-1)
               + ROT_GRIP_SCALE * np.linalg.norm(d[..., 3:GRIPPER_COLUMN], axis=-1)
               + ROT_GRIP_SCALE * np.abs(d[..., GRIPPER_COLUMN]))
    return per_row @ (DECAY ** np.arange(overlap))


def sample_chunks(bundle, samples: int, *args, **kwargs) -> np.ndarray:
    """(K, Tp, Da) chunks from `bundle.act(*args, **kwargs)`: one batch of K = `samples`, or for K = 1 the plain
    call (which a policy stand-in without batches also answers)."""
    if samples == 1:
        return bundle.act(*args, **kwargs)[None]
    return bundle.act(*args, samples=samples, **kwargs)


class Coherence:
    """One command's chunk picker (module doc): `pick` the candidates made at an observation time, and it keeps the
    one picked to compare the next tick's with. K = `samples`."""

    def __init__(self, samples: int = 1):
        self.samples = check_samples(samples)
        self.chose = 0  # ticks where the candidates were compared with an earlier chunk
        self.changed = 0  # and the closest was not the first sample
        self._last: tuple[np.ndarray, float] | None = None  # the chunk picked last and its observation time

    def pick(self, candidates: np.ndarray, t_obs: float, dt: float) -> np.ndarray:
        """(n, Da) the candidate of (K, n, Da) to run, for the observation at `t_obs` [s] with `dt` [s] between
        rows; it becomes the earlier chunk for the next pick."""
        candidates = np.asarray(candidates)
        k = 0
        if self._last is not None and len(candidates) > 1:
            earlier, t_last = self._last
            shift = int(round((t_obs - t_last) / dt))
            if 0 < shift < len(earlier):
                k = int(np.argmin(chunk_distance(candidates, earlier, shift)))
                self.chose += 1
                self.changed += k != 0
        self._last = (candidates[k], float(t_obs))
        return candidates[k]

    def forget(self) -> None:
        """Nothing to be coherent with: the arm was moved by something other than the policy (a look, a retreat)."""
        self._last = None


__all__ = ["Coherence", "check_samples", "chunk_distance", "sample_chunks", "MAX_SAMPLES"]
