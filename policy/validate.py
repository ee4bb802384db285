"""Validation during training: the same measures on episodes the model never trained on and on episodes it
did, so the gap between them shows when the model memorizes scenes instead of learning the skill.

A run's open-loop loss can keep falling while the closed-loop policy fails in new scenes: a run on 1495
pick_place episodes located the grasp point from its images to 1.4 cm on training episodes and to 11.6 cm
on unseen ones (always answering the training mean: 18 cm). Measured every `val_every` steps on fixed
samples, fixed noise and fixed diffusion timesteps (so successive rows compare), with the EMA weights and
centre crops:

  loss      the denoising MSE (noise prediction; velocity with objective = flow: not comparable across them)
  chunk_cm  median distance between the positions of the chunk the policy samples (its inference_steps, fixed
            noise) and the recorded ones, over the executed actions: what the policy would do, comparable
            across objectives and sampler steps (a multimodal policy may sample another good way: not 0)
  grasp_cm  median error of the auxiliary head's grasp point (only with aux_target_weight > 0)
  pregrasp_cm  the same over the samples observed before the gripper closes, where the policy aims: after
            the grasp the object rides in the fingers and the point it was taken from is not in the images
  release_cm  median error of the aux head's release point over the samples observed while the object is
            carried, before the gripper opens: how well the policy sees where to let go
  prerelease_cm  the release point's error over the samples observed before the grasp, where nothing is held
            over the scene: whether the head knows the place and loses it while carrying (stack: the block below)
  grasp<i>_cm  the grasp point's error over the samples on their way to their episode's grasp i (1: the
            second), for data with tasks that grasp more than once (drawer_put: the object after the handle):
            whether the head follows the task to its next stage or keeps pointing at the first grasp
  axis_deg  with aux_grasp_axis: median error of the head's grasp yaw (degrees, 0-90) over the samples observed
            before the grasp of an object with a grasp axis (a bar) while the gripper is still UNALIGNED_DEG or
            more off it: does it see which way the bar lies (nearer, the label is about "no turn", and a head
            that always says so would score well); guess_axis_deg: that head's error on the same samples

each as val_* (held-out episodes, `val_fraction`) and fit_* (the same number of training samples); on data of
several task families also val_pregrasp_cm.<family>, val_release_cm.<family>, val_prerelease_cm.<family> and
val_chunk_cm.<family>
(held-out samples of that family only), because a mixed median hides a family the head does not see (a drawer
handle among pick_place scenes); and guess_grasp_cm: the error of always answering the training samples' mean
grasp point, the scale against which a grasp_cm reads (it differs between aux_target_frame base and tcp: 18.8
vs 13.3 cm on 500 episodes).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import default_collate

from policy.data import AUX_TCP_SCALE, PolicyDataset, finish_images, to_device
from policy.grasp_axis import angle_error_deg


UNALIGNED_DEG = 20.0


def _by_family(name: str, measure: str, values: np.ndarray, family: np.ndarray, where: np.ndarray) -> dict:
    """{name_measure.family: median} over the samples `where` of each family, for held-out samples of several."""
    families = sorted(set(family.tolist()))
    if name != "val" or len(families) < 2:
        return {}
    return {f"{name}_{measure}.{f}": float(np.median(values[where & (family == f)]))
            for f in families if (where & (family == f)).any()}


class Validator:
    def __init__(self, val: PolicyDataset, fit: PolicyDataset, samples: int = 512, batch: int = 64, seed: int = 0,
                 chunks: bool = True):
        """chunks=False leaves chunk_cm out (pretraining: its denoiser is not trained)."""
        rng = np.random.default_rng(seed)
        self.sets = {name: (ds, rng.choice(len(ds), min(samples, len(ds)), replace=False))
                     for name, ds in (("val", val), ("fit", fit))}
        self.batch, self.seed, self.chunks = batch, seed, chunks
        self.normalizer = fit.normalizer
        points = {name: self._metres(np.stack([ds.aux_target(int(i))[:3].numpy() for i in idx]))
                  for name, (ds, idx) in self.sets.items()}
        miss = np.linalg.norm(points["val"] - points["fit"].mean(axis=0), axis=1)
        self.guess_cm = float(np.median(miss) * 100)

    @torch.no_grad()
    def __call__(self, model, device) -> dict:
        was_training = model.training
        model.eval()
        out = {}
        for name, (ds, idx) in self.sets.items():
            g = torch.Generator().manual_seed(self.seed)
            losses, errors, chunk, axis = [], [], [], []
            before = np.array([ds.before_grasp(int(i)) for i in idx])
            carrying = np.array([ds.carrying(int(i)) for i in idx])
            family = np.array([ds.task_of(int(i)) for i in idx])
            ahead = np.array([ds.grasp_ahead(int(i)) for i in idx]).reshape(-1, 2)
            for lo in range(0, len(idx), self.batch):
                batch = to_device(default_collate([ds[int(i)] for i in idx[lo:lo + self.batch]]), device)
                batch = finish_images(batch) if ds.uint8_images else batch
                noise = torch.randn(batch["action"].shape, generator=g).to(device)
                t = torch.randint(0, model.cfg.num_train_timesteps, (noise.shape[0],), generator=g).to(device)
                features = model.obs_encoder(batch["images"], batch["proprio"], batch["text"])
                cond = model.cond_from(features, batch["proprio"])
                pred, target = model.denoise_target(cond, batch["action"], noise, t)
                losses.append((pred - target).square().mean(dim=(1, 2)).cpu())
                if self.chunks:
                    chunk.append(self._chunk_cm(model, cond, batch["action"], g))
                if model.aux_head is not None:
                    pred = model.aux_points(features)[:, :6].float().cpu().numpy()
                    want = batch["aux"][:, :6].cpu().numpy()
                    errors.append(np.stack([self._metres(pred[:, j:j + 3]) - self._metres(want[:, j:j + 3])
                                            for j in (0, 3)], axis=1))
                    if model.cfg.aux_grasp_axis:
                        axis.append((model.aux_points(features)[:, 6:8].float().cpu().numpy(),
                                     batch["aux"][:, 6:8].cpu().numpy()))
            out[f"{name}_loss"] = float(torch.cat(losses).mean())
            if chunk:
                chunk = np.concatenate(chunk)
                out[f"{name}_chunk_cm"] = float(np.median(chunk))
                out.update(_by_family(name, "chunk_cm", chunk, family, np.ones(len(idx), bool)))
            if errors:
                miss = np.linalg.norm(np.concatenate(errors), axis=2) * 100  # (samples, grasp|release)
                out[f"{name}_grasp_cm"] = float(np.median(miss[:, 0]))
                if before.any():
                    out[f"{name}_pregrasp_cm"] = float(np.median(miss[before, 0]))
                    out.update(_by_family(name, "pregrasp_cm", miss[:, 0], family, before))
                    out[f"{name}_prerelease_cm"] = float(np.median(miss[before, 1]))
                    out.update(_by_family(name, "prerelease_cm", miss[:, 1], family, before))
                for g in range(1, int(ahead[:, 0].max(initial=0)) + 1 if name == "val" else 1):
                    on_way = (ahead[:, 0] == g) & ahead[:, 1].astype(bool)
                    if on_way.any():
                        out[f"val_grasp{g}_cm"] = float(np.median(miss[on_way, 0]))
                        out.update(_by_family(name, f"grasp{g}_cm", miss[:, 0], family, on_way))
                if carrying.any():
                    out[f"{name}_release_cm"] = float(np.median(miss[carrying, 1]))
                    out.update(_by_family(name, "release_cm", miss[:, 1], family, carrying))
                out["guess_grasp_cm"] = self.guess_cm
            if axis:
                pred, want = (np.concatenate(a) for a in zip(*axis))
                unaligned = want[:, 0] < np.cos(np.radians(2 * UNALIGNED_DEG))  # |2d| >= 2 UNALIGNED_DEG
                bar = before & (np.linalg.norm(want, axis=1) > 0.5) & unaligned
                if bar.any():
                    out[f"{name}_axis_deg"] = float(np.median(angle_error_deg(pred[bar], want[bar])))
                    if name == "val":
                        out["guess_axis_deg"] = float(np.median(angle_error_deg(np.array([[1.0, 0.0]]), want[bar])))
        model.train(was_training)
        return out

    def _chunk_cm(self, model, cond: torch.Tensor, action: torch.Tensor, g: torch.Generator) -> np.ndarray:
        """Per sample: mean position distance (cm) of the executed rows of a sampled chunk from the recorded."""
        from policy.sampling import sample

        cfg = model.cfg
        noise = cfg.noise_scale * torch.randn(action.shape, generator=g).to(action.device)
        ex = slice(cfg.obs_horizon - 1, cfg.obs_horizon - 1 + cfg.action_horizon)
        got = self.normalizer.unnormalize_action(sample(model, cond, noise)[:, ex].float().cpu().numpy())
        want = self.normalizer.unnormalize_action(action[:, ex].float().cpu().numpy())
        return np.linalg.norm(got[..., :3] - want[..., :3], axis=-1).mean(axis=1) * 100

    def _metres(self, p: np.ndarray) -> np.ndarray:
        """Aux grasp points in the head's units -> metres (tcp frame: a scale; base frame: the action stats)."""
        ds = self.sets["fit"][0]
        if ds.cfg.aux_target_frame == "tcp":
            return p * AUX_TCP_SCALE
        a = np.zeros((len(p), ds.cfg.action_dim), np.float32)
        a[:, :3] = p
        return self.normalizer.unnormalize_action(a)[:, :3]


def validate_model(source, data, samples: int = 1024, val_fraction: float | None = None, threads: int | None = None,
                   embedder=None) -> dict:
    """The measures above for a trained run's EMA model or a bundle's (rebuilt from its graphs) on the held-out
    episodes of `data` (val_fraction: the source's, unless given; normalized with the source's stats): a model
    held to data it did not train on, e.g. a bundle of one family to the episodes of five. A `sudd pretrain`
    run's denoiser never trained: its chunks and denoising loss are left out."""
    import dataclasses
    from pathlib import Path

    from policy.bundle_import import is_bundle, model_from_bundle
    from policy.normalize import Normalizer
    from policy.train import load_run_model
    from policy.warm_start import is_pretrain_run

    if threads:
        torch.set_num_threads(threads)
    pretrained_only = False
    if is_bundle(source):
        model, normalizer, _ = model_from_bundle(source)
    else:
        model, _, _ = load_run_model(source)
        normalizer = Normalizer.load(Path(source) / "stats.npz")
        pretrained_only = is_pretrain_run(source)
    cfg = model.cfg if val_fraction is None else dataclasses.replace(model.cfg, val_fraction=val_fraction)
    if not 0.0 < cfg.val_fraction <= 0.5:
        raise ValueError(f"{source} was trained with val_fraction {cfg.val_fraction}: no episodes of its own are "
                         "held out; give a val_fraction in (0, 0.5] (those episodes may include trained ones)")
    if embedder is None:
        from policy.text import default_embedder

        embedder = default_embedder()
    kw = dict(train=False, normalizer=normalizer, embedder=embedder, uint8_images=True, max_cache_bytes=0)
    val = PolicyDataset(data, cfg, split="val", **kw)
    fit = PolicyDataset(data, cfg, split="train", **kw)
    out = Validator(val, fit, samples=samples, chunks=not pretrained_only)(model.eval(), torch.device("cpu"))
    return {k: v for k, v in out.items() if not (pretrained_only and k.endswith("_loss"))}  # an untrained denoiser's
