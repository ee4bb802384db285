"""Inference in torch: the sampling loop (DDIM, or Euler for flow matching) and the whole observation ->
action-chunk path.

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
from policy.schedule import ddim_schedule, flow_schedule, schedule_steps, step_function
from policy.stage import with_stage


def schedule_for(model: DiffusionPolicy, steps: int | None = None) -> dict:
    """The sampler's schedule for the model's objective: DDIM's (timesteps, alpha_bar, alpha_bar_prev) or
    flow matching's (timesteps, sigma, sigma_next)."""
    cfg = model.cfg
    n = steps or cfg.inference_steps
    if cfg.objective == "flow":
        return flow_schedule(cfg.num_train_timesteps, n)
    return ddim_schedule(cfg.num_train_timesteps, n, cfg.beta_schedule)


@torch.no_grad()
def sample(model: DiffusionPolicy, cond: torch.Tensor, noise: torch.Tensor, schedule: dict | None = None
           ) -> torch.Tensor:
    """(B, G) global cond, (B, Tp, Da) initial noise -> (B, Tp, Da) normalized actions: deterministic DDIM,
    or Euler steps of the velocity for a flow-matching model.

    The cond's FiLM projection is computed once for all steps, as the exported graphs do."""
    sch = schedule or schedule_for(model)
    step = step_function(sch)
    film = model.unet.condition(cond)
    x = noise
    for t, c, c_next in schedule_steps(sch):
        out = model.unet.denoise(x, torch.full((x.shape[0],), int(t), dtype=torch.int64, device=x.device), film)
        x = step(x, out, c, c_next, model.cfg.clip_sample)
    return x


@torch.no_grad()
def predict_chunk(model: DiffusionPolicy, normalizer: Normalizer, images: dict[str, np.ndarray],
                  proprio: np.ndarray, text_embedding: np.ndarray, noise: np.ndarray, stage: int = 0) -> np.ndarray:
    """One observation (no batch axis) -> (Tp, Da) absolute actions.

    images: camera -> (To, H, W, 3) uint8; proprio (To, Dp) raw; text_embedding (cfg.text_input_dim,); noise (Tp, Da);
    stage: grasp cycles completed so far (policy.stage; read only with cfg.stage_bins).
    """
    model.eval()
    imgs = {c: prepare_images(torch.from_numpy(np.asarray(images[c]))[None], model.cfg.crop_size)
            for c in model.cfg.cameras}
    p = torch.from_numpy(with_stage(normalizer.normalize_proprio(proprio), stage, model.cfg.stage_bins))[None]
    cond = model.encode(imgs, p, torch.from_numpy(np.asarray(text_embedding, np.float32))[None])
    x = sample(model, cond, torch.from_numpy(np.asarray(noise, np.float32))[None])
    a = orthonormalize_rot6d(normalizer.unnormalize_action(x[0].numpy()))
    return from_tcp(a, np.asarray(proprio)[-1, :9]) if model.cfg.action_frame == "tcp" else a
