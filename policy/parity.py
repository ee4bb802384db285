"""How far an exported bundle is from the torch policy, and what fp16 weight storage costs (manifest figures).

`check_parity`: torch vs the bundle on random observations - cond, every denoising step along the bundle's
own DDIM trajectory, and the final absolute chunk from the same noise; export refuses to publish over
STEP_TOL / CHUNK_TOL. With fp16 weight storage the torch side is the fp16-rounded model, so this stays a
check of the export alone, exact to fp32 arithmetic.

`rounding_cost`: the fp16-rounded policy vs the unrounded one, both in torch, on the same observations and
noise: the largest difference of their chunks in normalized action units ([-1, 1] is the demonstrated range)
and of their position targets in metres, i.e. what storing the weights in half the bytes changes in what the
robot is asked to do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from policy.model import DiffusionPolicy, prepare_images
from policy.normalize import Normalizer
from policy.sampling import predict_chunk, sample
from policy.stage import with_stage

STEP_TOL, CHUNK_TOL = 1e-4, 1e-3


class ExportError(RuntimeError):
    """The exported graphs do not reproduce the torch policy; nothing was published."""


def _random_observations(cfg, normalizer: Normalizer, trials: int, seed: int):
    """(images, raw proprio, unit text embedding, noise, grasp cycles) per trial, inside the normalizer's proprio
    range; the cycles 0 .. stage_bins (past the last class too) when the policy reads them, else 0."""
    rng = np.random.default_rng(seed)
    H, W = cfg.image_size
    for _ in range(trials):
        images = {c: rng.integers(0, 256, (cfg.obs_horizon, H, W, 3), dtype=np.uint8) for c in cfg.cameras}
        lo, hi = normalizer.proprio_min, normalizer.proprio_max
        proprio = (lo + (hi - lo) * rng.random((cfg.obs_horizon, cfg.proprio_dim))).astype(np.float32)
        text = rng.normal(size=cfg.text_input_dim).astype(np.float32)
        text /= np.linalg.norm(text)
        noise = rng.normal(size=(cfg.pred_horizon, cfg.action_dim)).astype(np.float32)
        yield images, proprio, text, noise, int(rng.integers(0, cfg.stage_bins + 1)) if cfg.stage_bins else 0


def _inputs(model: DiffusionPolicy, normalizer: Normalizer, images: dict, proprio: np.ndarray, text: np.ndarray,
            stage: int):
    """One raw observation as the torch obs encoder reads it: (images, proprio, text), batch of one."""
    imgs = {c: prepare_images(torch.from_numpy(images[c])[None], model.cfg.crop_size) for c in model.cfg.cameras}
    p = with_stage(normalizer.normalize_proprio(proprio), stage, model.cfg.stage_bins)
    return imgs, torch.from_numpy(p)[None], torch.from_numpy(text)[None]


def _encode(model: DiffusionPolicy, normalizer: Normalizer, images: dict, proprio: np.ndarray, text: np.ndarray,
            stage: int):
    return model.encode(*_inputs(model, normalizer, images, proprio, text, stage))


@torch.no_grad()
def rounding_cost(fp32: DiffusionPolicy, rounded: DiffusionPolicy, normalizer: Normalizer, trials: int = 3,
                  seed: int = 1) -> dict:
    """Max |chunk(rounded) - chunk(fp32)|, normalized and (position, columns 0:3) in metres; same inputs."""
    worst, pos = 0.0, 0.0
    for images, proprio, text, noise, stage in _random_observations(fp32.cfg, normalizer, trials, seed):
        x = [sample(m, _encode(m, normalizer, images, proprio, text, stage), torch.from_numpy(noise)[None])[0].numpy()
             for m in (fp32, rounded)]
        worst = max(worst, float(np.abs(x[0] - x[1]).max()))
        a = [normalizer.unnormalize_action(v) for v in x]
        pos = max(pos, float(np.abs(a[0][:, :3] - a[1][:, :3]).max()))
    return {"chunk_max_abs_diff_normalized": worst, "position_max_abs_diff_m": pos, "trials": trials}


@torch.no_grad()
def check_parity(model: DiffusionPolicy, normalizer: Normalizer, bundle_dir: str | Path, trials: int = 3,
                 seed: int = 0, locator: DiffusionPolicy | None = None,
                 object_locator: DiffusionPolicy | None = None, turn_locator: DiffusionPolicy | None = None) -> dict:
    """torch vs the bundle (see the module docstring), and a goal locator's graph vs `locator` where given (the
    object locator's vs `object_locator`, the turn locator's vs `turn_locator`). Raises ExportError over tolerance."""
    from policy.bundle import Bundle

    b = Bundle.load(bundle_dir, warmup=False)
    worst = {"cond_max_abs_err": 0.0, "step_max_abs_err": 0.0, "chunk_max_abs_err": 0.0}
    for images, proprio, text, noise, stage in _random_observations(model.cfg, normalizer, trials, seed):
        trace: list = []
        chunk = b.act(images, proprio, text, noise=noise, trace=trace, stage=stage)
        cond = model.unet.condition(_encode(model, normalizer, images, proprio, text, stage))
        worst["cond_max_abs_err"] = max(worst["cond_max_abs_err"], float(np.abs(cond.numpy() - trace[0]).max()))
        for x, t, eps in trace[1:]:
            ref = model.unet.denoise(torch.from_numpy(x), torch.tensor([t]), torch.from_numpy(trace[0]))
            worst["step_max_abs_err"] = max(worst["step_max_abs_err"], float(np.abs(ref.numpy() - eps).max()))
        ref_chunk = predict_chunk(model, normalizer, images, proprio, text, noise, stage)
        worst["chunk_max_abs_err"] = max(worst["chunk_max_abs_err"], float(np.abs(ref_chunk - chunk).max()))
    if model.cfg.release_input:
        worst.update(_release_parity(model, normalizer, b, trials, seed))
    for graph, m in (("goal_locator", locator), ("object_locator", object_locator), ("turn_locator", turn_locator)):
        if m is not None:
            worst[f"{graph}_max_abs_err"] = _locator_parity(m, normalizer, b, trials, seed, graph)
    worst.update(trials=trials, step_tol=STEP_TOL, chunk_tol=CHUNK_TOL)
    over = [k for k in ("cond_max_abs_err", "step_max_abs_err", "release_cond_max_abs_err", "aux_points_max_abs_err",
                        "grasp_cond_max_abs_err", "goal_locator_max_abs_err", "object_locator_max_abs_err",
                        "turn_locator_max_abs_err")
            if worst.get(k, 0.0) > STEP_TOL]
    if over or worst["chunk_max_abs_err"] > CHUNK_TOL:
        raise ExportError(f"exported graphs disagree with torch: {worst}")
    return worst


def _release_parity(model: DiffusionPolicy, normalizer: Normalizer, b, trials: int, seed: int) -> dict:
    """A bundle with release_input: its cond with a given release point (and with grasp_input a given grasp
    point, alone) and its aux_points output vs torch."""
    from policy.graph_frames import with_grasp, with_release

    worst = {"release_cond_max_abs_err": 0.0, "aux_points_max_abs_err": 0.0}
    if model.cfg.grasp_input:
        worst["grasp_cond_max_abs_err"] = 0.0
    rng = np.random.default_rng(seed + 1)
    for images, proprio, text, _, stage in _random_observations(model.cfg, normalizer, trials, seed):
        release = np.append(rng.uniform([-0.4, 0.2, 0.0], [0.4, 0.8, 0.3]), 1.0).astype(np.float32)
        cond, points = b._encode(images, proprio, text, stage, release)
        imgs, p, t = _inputs(model, normalizer, images, proprio, text, stage)
        features = model.obs_encoder(imgs, p, t)
        head = model.aux_points(features)
        ref = model.unet.condition(model.cond_from(features, p, with_release(head, torch.from_numpy(release)[None])))
        worst["release_cond_max_abs_err"] = max(worst["release_cond_max_abs_err"], float(np.abs(ref.numpy() - cond).max()))
        worst["aux_points_max_abs_err"] = max(worst["aux_points_max_abs_err"], float(np.abs(head.numpy() - points).max()))
        if model.cfg.grasp_input:
            grasp = np.append(rng.uniform([-0.4, 0.2, 0.0], [0.4, 0.8, 0.3]), 1.0).astype(np.float32)
            cond = b._encode(images, proprio, text, stage, None, grasp)[0]
            given = with_grasp(head, torch.from_numpy(grasp)[None], p, model.proprio_scale, model.proprio_offset)
            ref = model.unet.condition(model.cond_from(features, p, given))
            worst["grasp_cond_max_abs_err"] = max(worst["grasp_cond_max_abs_err"],
                                                  float(np.abs(ref.numpy() - cond).max()))
    return worst


def _locator_parity(locator: DiffusionPolicy, normalizer: Normalizer, b, trials: int, seed: int,
                    graph: str = "goal_locator") -> float:
    """The largest |the locator graph's points - the torch locator's| over random observations."""
    worst = 0.0
    for images, proprio, text, _, stage in _random_observations(locator.cfg, normalizer, trials, seed + 2):
        feeds = {f"image_{c}": images[c][None] for c in locator.cfg.cameras}
        got = b.sessions[graph].run(None, {**feeds, "text_embedding": text[None]})[0]
        imgs, p, t = _inputs(locator, normalizer, images, proprio, text, stage)
        ref = locator.aux_points(locator.obs_encoder(imgs, p, t)).numpy()
        worst = max(worst, float(np.abs(ref - got).max()))
    return worst
