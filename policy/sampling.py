"""Inference in torch: the DDIM loop and the whole observation -> action-chunk path.

This is the reference the exported bundle is checked against: `predict_chunk` takes exactly what
`policy.bundle.Bundle.act` takes (full-size uint8 images, raw proprio, the text embedding, the initial noise)
and returns what it returns (absolute actions with rot6d re-orthonormalized), through the same centre crop
(`policy.model.prepare_images`), the same schedule (`policy.schedule.ddim_schedule`) and the same update.
"""

from __future__ import annotations

import numpy as np
import torch

from policy.action_frame import from_tcp, orthonormalize_rot6d
from policy.model import DiffusionPolicy, prepare_images
from policy.normalize import Normalizer
from policy.schedule import ddim_schedule, ddim_step


def schedule_for(model: DiffusionPolicy, steps: int | None = None) -> dict:
    cfg = model.cfg
    return ddim_schedule(cfg.num_train_timesteps, steps or cfg.inference_steps, cfg.beta_schedule)


@torch.no_grad()
def ddim_sample(model: DiffusionPolicy, cond: torch.Tensor, noise: torch.Tensor, schedule: dict | None = None
                ) -> torch.Tensor:
    """(B, G) global cond, (B, Tp, Da) initial noise -> (B, Tp, Da) normalized actions (deterministic DDIM).

    The cond's FiLM projection is computed once for all steps, as the exported graphs do."""
    sch = schedule or schedule_for(model)
    film = model.unet.condition(cond)
    x = noise
    for t, ab, ab_prev in zip(sch["timesteps"], sch["alpha_bar"], sch["alpha_bar_prev"]):
        eps = model.unet.denoise(x, torch.full((x.shape[0],), int(t), dtype=torch.int64, device=x.device), film)
        x = ddim_step(x, eps, ab, ab_prev, model.cfg.clip_sample)
    return x


@torch.no_grad()
def predict_chunk(model: DiffusionPolicy, normalizer: Normalizer, images: dict[str, np.ndarray],
                  proprio: np.ndarray, text_embedding: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """One observation (no batch axis) -> (Tp, Da) absolute actions.

    images: camera -> (To, H, W, 3) uint8; proprio (To, Dp) raw; text_embedding (384,); noise (Tp, Da).
    """
    model.eval()
    imgs = {c: prepare_images(torch.from_numpy(np.asarray(images[c]))[None], model.cfg.crop_size)
            for c in model.cfg.cameras}
    p = torch.from_numpy(normalizer.normalize_proprio(proprio))[None]
    cond = model.encode(imgs, p, torch.from_numpy(np.asarray(text_embedding, np.float32))[None])
    x = ddim_sample(model, cond, torch.from_numpy(np.asarray(noise, np.float32))[None])
    a = orthonormalize_rot6d(normalizer.unnormalize_action(x[0].numpy()))
    return from_tcp(a, np.asarray(proprio)[-1, :9]) if model.cfg.action_frame == "tcp" else a
