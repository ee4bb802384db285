"""The frozen image encoders' features of every training frame, computed once (config `feature_cache`).

Why: with `freeze_pretrained` the image encoders no longer change, yet each training step would still read,
crop, jitter and encode 64 x To x cameras images, most of a CPU step's time. Encoding every frame once, for
a few augmented copies, leaves the step with the part that learns (proprio and text encoders, denoiser).

The table has `copies` blocks of one row per frame of the dataset (episode after episode, as
`PolicyDataset.frame_offset` counts them): row c * num_frames + f is frame f's features (cameras x
image_feature_dim, camera by camera as ObsEncoder lays them out), encoded with its episode's instruction
(the encoders are FiLMed by it). Copy 0 is centre-cropped and unjittered, what inference sees; the others get
the training crop and colour jitter, drawn per frame (training draws one per sample: the same thing at
obs_horizon 1). Copies are drawn from `seed`, so a rebuilt table is the same table.
"""

from __future__ import annotations

import numpy as np
import torch

from policy.data import PolicyDataset, color_jitter, crop, jitter_factors
from policy.model import DiffusionPolicy


@torch.no_grad()
def image_feature_table(model: DiffusionPolicy, ds: PolicyDataset, copies: int, *, seed: int = 0,
                        device: torch.device | str = "cpu", batch: int = 256, progress: bool = True) -> torch.Tensor:
    """(copies * ds.num_frames, cameras x image_feature_dim) float32 on `device`: see the module docstring."""
    from tqdm import tqdm

    cfg = model.cfg
    if copies < 1:
        raise ValueError(f"copies = {copies}: expected at least 1")
    encoder, was_training = model.obs_encoder, model.obs_encoder.training
    encoder.eval()
    width = len(cfg.cameras) * cfg.image_feature_dim
    table = torch.empty(copies * ds.num_frames, width, device=device)
    h, w = cfg.crop_size
    bar = tqdm(total=copies * ds.num_frames, disable=not progress, desc="encode frames", unit="frame")
    for k, episode in enumerate(ds.episodes):
        T, first = ds.lengths[k], int(ds.frame_offset[k])
        text = ds.text_table[ds.text_row[ds.instructions[k]]].to(device)
        frames = {c: ds.episode_frames(k, c, np.arange(T)) for c in cfg.cameras}  # (T, H, W, 3) uint8
        for copy in range(copies):
            rng = np.random.default_rng([seed, int(episode), copy])
            for lo in range(0, T, batch):
                hi = min(T, lo + batch)
                images = {}
                for c in cfg.cameras:
                    x = frames[c][lo:hi]
                    if copy == 0:
                        x = crop(x, cfg.crop_size)
                    else:
                        H, W = x.shape[1:3]
                        x = np.stack([crop(f[None], cfg.crop_size, int(rng.integers(0, H - h + 1)),
                                           int(rng.integers(0, W - w + 1)))[0] for f in x])
                    x = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).float() / 255.0
                    if copy:
                        factors = np.stack([jitter_factors(rng, cfg.color_jitter) for _ in range(hi - lo)])
                        x = color_jitter(x[:, None], torch.from_numpy(factors))[:, 0]
                    images[c] = x[:, None].to(device)  # (n, To=1, 3, h, w)
                feats = encoder.camera_features(images, text.expand(hi - lo, -1))
                table[copy * ds.num_frames + first + lo:copy * ds.num_frames + first + hi] = feats[:, 0]
                bar.update(hi - lo)
    bar.close()
    encoder.train(was_training)
    return table
