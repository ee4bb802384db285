"""Normalization of proprioception and actions, owned by the policy and shipped in the bundle (stats.npz).

Per dimension, x_norm = x * scale + offset:

- positions, gripper and joint angles: min/max over the training data -> [-1, 1]. Min/max (not mean/std)
  because the DDIM sampler clips its x0 estimate to [-1, 1]: every action target the policy can emit then
  lies inside the range seen in the demonstrations (a workspace bound for free), and no dimension is cut off.
- rot6d (two columns of a rotation matrix): left as is (scale 1, offset 0). Its entries already lie in
  [-1, 1], and rescaling them per dimension would skew the Gram-Schmidt re-orthonormalization the runtime
  applies to the unnormalized output; a constant orientation across the data must not become a 0/0.
- a dimension that never varies (range < 1e-4, e.g. a gripper always open in a dataset) maps to 0 with
  scale 1, so unnormalization returns the constant exactly instead of amplifying noise by 1/range.

Layouts come from datagen.schema: proprio = pos 3 | rot6d 6 | gripper 1 | q 6; action = pos 3 | rot6d 6 | gripper 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

MIN_RANGE = 1e-4
ROT6D_PROPRIO = slice(3, 9)
ROT6D_ACTION = slice(3, 9)
STAT_KEYS = ("proprio_scale", "proprio_offset", "proprio_min", "proprio_max",
             "action_scale", "action_offset", "action_min", "action_max")


def fit_minmax(x: np.ndarray, identity: slice | None = None) -> tuple[np.ndarray, ...]:
    """(scale, offset, min, max) mapping each column of x (N, D) to [-1, 1]; `identity` columns untouched."""
    x = np.asarray(x, np.float64)
    lo, hi = x.min(axis=0), x.max(axis=0)
    rng = hi - lo
    scale = np.where(rng < MIN_RANGE, 1.0, 2.0 / np.maximum(rng, MIN_RANGE))
    offset = np.where(rng < MIN_RANGE, -(hi + lo) / 2, -1.0 - lo * scale)
    if identity is not None:
        scale[identity], offset[identity] = 1.0, 0.0
    return tuple(a.astype(np.float32) for a in (scale, offset, lo, hi))


@dataclass(frozen=True)
class Normalizer:
    """Affine per-dimension maps for proprio (Dp,) and actions (Da,), float32."""

    proprio_scale: np.ndarray
    proprio_offset: np.ndarray
    proprio_min: np.ndarray
    proprio_max: np.ndarray
    action_scale: np.ndarray
    action_offset: np.ndarray
    action_min: np.ndarray
    action_max: np.ndarray

    @classmethod
    def fit(cls, proprio: np.ndarray, action: np.ndarray) -> "Normalizer":
        p = fit_minmax(proprio, ROT6D_PROPRIO if proprio.shape[1] >= 9 else None)
        a = fit_minmax(action, ROT6D_ACTION if action.shape[1] >= 9 else None)
        return cls(*p, *a)

    @classmethod
    def identity(cls, proprio_dim: int, action_dim: int) -> "Normalizer":
        """No-op stats (for a freshly initialized model with no dataset, e.g. the latency bench)."""
        p, a = np.ones(proprio_dim, np.float32), np.ones(action_dim, np.float32)
        return cls(p, 0 * p, -p, p, a, 0 * a, -a, a)

    def normalize_proprio(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, np.float32) * self.proprio_scale + self.proprio_offset).astype(np.float32)

    def normalize_action(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, np.float32) * self.action_scale + self.action_offset).astype(np.float32)

    def unnormalize_action(self, y: np.ndarray) -> np.ndarray:
        return ((np.asarray(y, np.float32) - self.action_offset) / self.action_scale).astype(np.float32)

    def unnormalize_proprio(self, y: np.ndarray) -> np.ndarray:
        return ((np.asarray(y, np.float32) - self.proprio_offset) / self.proprio_scale).astype(np.float32)

    def to_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in STAT_KEYS}

    def save(self, path: str | Path) -> None:
        np.savez(path, **self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "Normalizer":
        with np.load(path) as z:
            missing = [k for k in STAT_KEYS if k not in z]
            if missing:
                raise ValueError(f"{path}: normalization stats miss {missing}")
            return cls(**{k: z[k].astype(np.float32) for k in STAT_KEYS})
