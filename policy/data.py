"""Training samples from an episode dataset: (To observation steps, Tp action steps, the instruction).

Windows follow Diffusion Policy's sequence sampler. A sample is a start step s; observations are steps
s .. s+To-1 (the last one is "now"), actions s .. s+Tp-1, of which the runtime executes To-1 .. To-1+Ta-1.
Indices outside the episode are clamped: the first step repeats before the start (the robot "was" there),
the last step repeats after the end (the robot holds still once done). s ranges over
[-(To-1), T-Tp+Ta-1], so a window pads at most To-1 steps before and Ta-1 steps after the episode: every
chunk the runtime executes ends inside or right after real data.

Episodes: verified successes only by default (the label the data generator chose: meta["label"]["value"],
or the synthetic episodes' meta["label"]["success"], else meta["success"]); `include_failures` keeps all.

Actions: as recorded (absolute targets, normalized), or with `action_frame = "tcp"` each window's chunk
turned relative to the TCP pose at its "now" step before normalizing (policy.action_frame); the stats are
then fitted on every window's chunk in its own frame.

Language: the root instruction; with `subtask_language_prob` > 0 a sample is instead conditioned on the
label of the subtask running at "now" (not while recovering). Each distinct string is embedded ONCE with the
frozen MiniLM encoder; samples carry a row of that table.

Speed on 2 cores: low-dimensional arrays are always held in memory, already normalized; images too when
the dataset fits `max_cache_bytes` (default: half the memory available at start; decoding zarr chunks per
sample would dominate a CPU training step: measured 0.77 vs 0.45 s per step for 300 pick_place episodes),
else each sample reads only the chunks its window touches. Augmentation (train only): one random crop per
camera and window (the same crop for all To frames, so motion between frames stays real) and colour
jitter (brightness, contrast, saturation); evaluation uses the centre crop, exactly as the exported graph.
Randomness comes from a per-sample seed (`dataset[(index, seed)]`), so training can replay any step exactly.

`uint8_images=True` (what training uses) leaves the last step to the batch: samples carry the cropped
frames as uint8 plus their jitter factors, and `finish_images` scales and jitters a whole batch where it
lands. On a GPU that moves a quarter of the bytes through the DataLoader and pinned memory and takes the
per-pixel arithmetic off the CPU workers: measured on an H100 with 14 workers, the float path fed only
~9.5 steps/s of batch 256 with the GPU 22-33 % busy.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from datagen.release_offsets import release_offset_at
from datagen.schema import (episode_success, grasp_and_release_per_step, gripper_levels,  # noqa: F401 (policy.data API)
                            grasp_and_release_steps, perturbed_actions)
from datagen.store import Dataset as EpisodeStore
from policy.action_frame import points_to_tcp, relative_windows, to_tcp
from policy.config import AUX_TCP_SCALE, PolicyConfig  # noqa: F401 (AUX_TCP_SCALE: policy.data API)
from policy.grasp_axis import axis_label, episode_target_has_axis, yaw_of
from policy.instruction import embed_instructions
from policy.normalize import Normalizer
from policy.stage import GRIPPER_COLUMN, commands_in_effect, cycles_per_step, with_stage


# the collector holds a grasp this many steps after closing (datagen.primitives.GRASP_SECONDS at CONTROL_HZ)
HOLD_SETTLE_STEPS = 6


def available_memory() -> float:
    """Bytes of physical memory free now (Linux; 2 GB where the OS does not say)."""
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 2e9


def is_validation(meta: dict, fraction: float) -> bool:
    """Whether an episode belongs to the validation split: a hash of (task, seed), stable across runs."""
    digest = hashlib.sha256(f"{meta.get('task')}:{meta.get('seed')}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2**64 < fraction


def data_holdout(metas: list[dict]) -> dict[str, list[str]]:
    """Colours/shapes the data generator kept out (`sudd datagen --holdout-color`): an evaluation on them is
    a test of generalization, and `sudd eval` keeps them out of its in-distribution suite."""
    out: dict[str, set] = {"colors": set(), "shapes": set()}
    for m in metas:
        for key in out:
            out[key].update((m.get("holdout") or {}).get(key, ()))
    return {k: sorted(v) for k, v in out.items()}


def crop(frames: np.ndarray, size: tuple[int, int], top: int | None = None, left: int | None = None) -> np.ndarray:
    """(..., H, W, C) -> (..., h, w, C); centre crop unless the corner is given."""
    H, W = frames.shape[-3:-1]
    h, w = size
    top = (H - h) // 2 if top is None else top
    left = (W - w) // 2 if left is None else left
    return frames[..., top:top + h, left:left + w, :]


def jitter_factors(rng: np.random.Generator, strength: float) -> np.ndarray:
    """(3,) float32 brightness, contrast, saturation factors in [1 - strength, 1 + strength] (ones if 0)."""
    if strength <= 0:
        return np.ones(3, np.float32)
    return rng.uniform(1 - strength, 1 + strength, size=3).astype(np.float32)


def color_jitter(x: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """(..., To, 3, h, w) float in [0, 1], (..., 3) factors -> same, one brightness/contrast/saturation for
    all To frames of a sample (a sample: the leading dims); contrast pivots on each frame's mean."""
    b, c, s = (factors[..., j].reshape(*factors.shape[:-1], 1, 1, 1, 1) for j in range(3))
    x = x * b
    mean = x.mean(dim=(-3, -2, -1), keepdim=True)
    x = (x - mean) * c + mean
    gray = 0.299 * x[..., 0:1, :, :] + 0.587 * x[..., 1:2, :, :] + 0.114 * x[..., 2:3, :, :]
    x = (x - gray) * s + gray
    return x.clamp(0.0, 1.0)


def finish_images(batch: dict) -> dict:
    """A collated batch of `uint8_images` samples -> the float batch the model takes, on the batch's device:
    images scaled to [0, 1] and colour-jittered by each sample's factors (popped from the batch)."""
    factors = batch.pop("jitter")
    batch["images"] = {c: color_jitter(x.float() / 255.0, factors) for c, x in batch["images"].items()}
    return batch


def to_device(batch, dev):
    """A (nested dict of) collated tensor(s) moved to `dev` (asynchronously from pinned memory)."""
    if isinstance(batch, dict):
        return {k: to_device(v, dev) for k, v in batch.items()}
    return batch.to(dev, non_blocking=True)


def grasp_and_release(normalized: np.ndarray, steps: tuple[int, int]) -> torch.Tensor:
    """(T, Da) normalized actions, `grasp_and_release_steps` -> (6,): the positions at those steps, in the
    actions' normalized units. The "base" auxiliary target of `aux_target_weight`: where the named object is
    and where it goes, both readable from the images."""
    t_close, t_open = steps
    return torch.from_numpy(np.concatenate([normalized[t_close, :3], normalized[t_open, :3]]).astype(np.float32))


def object_release_points(points: np.ndarray, cycle: np.ndarray, offsets: list[dict] | None) -> np.ndarray:
    """(T, 2, 3) grasp and release points per step, (T, 2) their steps, the episode's `release_offsets` -> the
    points with each release moved horizontally by where the placed object sat in the hand at it (config
    `release_point` "object"); a release with no recorded offset (a drawer's handle, older data) stays."""
    out = np.array(points, np.float64, copy=True)
    for step in np.unique(cycle[:, 1]):
        offset = release_offset_at(offsets, int(step))
        if offset is not None:
            out[cycle[:, 1] == step, 1, :2] += offset[:2]
    return out


def relative_to_tcp(points: np.ndarray, proprio: np.ndarray) -> torch.Tensor:
    """(2, 3) base-frame points [m], one raw proprio row (TCP position, rot6d, ...) -> (6,) the points in
    the TCP frame over AUX_TCP_SCALE. The "tcp" auxiliary target: an offset the wrist camera shows the
    same way in every scene, where an absolute position has to be worked out from the scene camera."""
    rel = points_to_tcp(points, np.asarray(proprio)[:9])
    return torch.from_numpy((rel / AUX_TCP_SCALE).reshape(6).astype(np.float32))


def aux_point_target(points: np.ndarray, proprio: np.ndarray, release_frame: str = "tcp") -> torch.Tensor:
    """The aux head's point target (6,): `relative_to_tcp`, except that with release_frame "base" the release
    point stays in the base frame (over the same scale): where the bin is, the same on every frame of an episode
    (cfg.aux_release_frame; the model turns it relative to the gripper for the denoiser)."""
    target = relative_to_tcp(points, proprio)
    if release_frame == "base":
        target[3:6] = torch.from_numpy((np.asarray(points)[1] / AUX_TCP_SCALE).astype(np.float32))
    return target


class PolicyDataset(torch.utils.data.Dataset):
    """Map-style dataset of policy samples; item = index or (index, seed). See the module docstring.

    A sample: {"images": {camera: (To, 3, h, w) float32 in [0, 1]}, "proprio": (To, Dp) normalized,
    "action": (Tp, Da) normalized, "text": (384,) unit vector, "aux": (6,)}; with `uint8_images` the
    images are uint8 and "jitter" (3,) holds the colour factors for `finish_images`; with `read_images` False
    there are no images, and "frames" (To,) holds the rows of the sample's frames in a policy.feature_cache table
    (a random copy in training).
    """

    def __init__(self, data: str | Path | EpisodeStore, cfg: PolicyConfig, train: bool = True,
                 normalizer: Normalizer | None = None, embedder: Callable[[list[str]], np.ndarray] | None = None,
                 include_failures: bool | None = None, max_cache_bytes: float | None = None,
                 uint8_images: bool = False, split: str | None = None, read_images: bool = True):
        self.store = data if isinstance(data, EpisodeStore) else EpisodeStore(data)
        self.cfg, self.train, self.uint8_images = cfg, train, uint8_images
        include = self.include_failures = cfg.include_failures if include_failures is None else include_failures
        rows = self.store.episodes()
        self.episodes = [r["index"] for r in rows if include or episode_success(self.store.meta(r["index"]))]
        if split is not None:  # "train" or "val": cfg.val_fraction of the episodes are validation episodes
            if split not in ("train", "val"):
                raise ValueError(f"split must be 'train', 'val' or None, got {split!r}")
            self.episodes = [i for i in self.episodes
                             if is_validation(self.store.meta(i), cfg.val_fraction) == (split == "val")]
        if not self.episodes and split is not None:
            raise ValueError(f"{self.store.root}: val_fraction={cfg.val_fraction} leaves no {split} episodes "
                             f"of its {len(rows)}; use more episodes or another val_fraction")
        if not self.episodes:
            raise ValueError(f"{self.store.root}: none of its {len(rows)} episodes is a verified success "
                             f"(pass include_failures=True to train on all)")
        low = [self.store.window(i, fields=("proprio", "action", "subtask")) for i in self.episodes]
        for i, arrays in zip(self.episodes, low):
            if arrays["proprio"].shape[1] != cfg.proprio_dim or arrays["action"].shape[1] != cfg.action_dim:
                raise ValueError(f"episode {i}: proprio/action dims {arrays['proprio'].shape[1]}/"
                                 f"{arrays['action'].shape[1]} != config {cfg.proprio_dim}/{cfg.action_dim}")
        To, Tp, Ta = cfg.obs_horizon, cfg.pred_horizon, cfg.action_horizon
        relative = cfg.action_frame == "tcp"
        if normalizer is None:  # tcp frame: the stats of what the model learns, every window in its own frame
            actions = [relative_windows(a["action"], a["proprio"], To, Tp) if relative else a["action"] for a in low]
            normalizer = Normalizer.fit(np.concatenate([a["proprio"] for a in low]), np.concatenate(actions))
        self.normalizer = normalizer
        self.proprio = [self.normalizer.normalize_proprio(a["proprio"]) for a in low]
        # what the sampler reads: normalized targets (base frame), or the recorded ones that each window
        # turns relative to its own newest TCP pose before normalizing (tcp frame)
        self.action = [a["action"] if relative else self.normalizer.normalize_action(a["action"]) for a in low]
        self.tcp_pose = [a["proprio"][:, :9].astype(np.float64) for a in low]
        self.gripper_levels = gripper_levels([a["action"][:, -1] for a in low])
        self.subtask = [a["subtask"].astype(np.int64) for a in low]
        # per step: grasp cycles completed so far, from the gripper commands and closures (policy.stage)
        self.stage = ([cycles_per_step(commands_in_effect(a["action"]), a["proprio"][:, GRIPPER_COLUMN]) for a in low]
                      if cfg.stage_bins else None)
        # per step: the grasp it heads for and the release that grasp leads to (past injected failures)
        self.cycle = [grasp_and_release_per_step(a["action"], a["subtask"]) for a in low]
        self.grasp_step = [int(c[0, 0]) for c in self.cycle]
        self.release_step = [int(c[0, 1]) for c in self.cycle]
        if cfg.aux_target_frame == "tcp":
            self.aux_points = [a["action"][c, :3] for a, c in zip(low, self.cycle)]  # (T, 2, 3)
            if cfg.release_point == "object":
                self.aux_points = [object_release_points(p, c, self.store.meta(i).get("release_offsets"))
                                   for p, c, i in zip(self.aux_points, self.cycle, self.episodes)]
        if cfg.aux_grasp_axis:  # per step: the yaw of the grasp it heads for; per episode: whether it has an axis
            self.grasp_yaw = [yaw_of(a["action"][c[:, 0], 3:9]) for a, c in zip(low, self.cycle)]
            self.has_axis = [episode_target_has_axis(self.store.meta(i)) for i in self.episodes]
        self.lengths = [len(a["action"]) for a in low]
        self.tasks = [self.store.meta(i)["task"] for i in self.episodes]
        self._language(embedder)
        # no window whose chunk holds a step of an injected failure (datagen.schema.PERTURBED): the data shows
        # how to recover from one, never how to make one
        clean = [np.concatenate([[0], np.cumsum(perturbed_actions(a["subtask"]))]) for a in low]
        # an episode whose grasps closed off the plan on purpose may train only from its first hold on
        # (cfg.grasp_noise_windows): the newest observation at least the grasp's hold past its close
        first = [self.grasp_step[k] + HOLD_SETTLE_STEPS if cfg.grasp_noise_windows == "after_grasp"
                 and self.store.meta(i).get("grasp_noise_cm") else -To for k, i in enumerate(self.episodes)]
        self.index = [(k, s) for k, T in enumerate(self.lengths)
                      for s in range(-(To - 1), max(-(To - 1), T - Tp + Ta - 1) + 1)
                      if clean[k][min(T, s + Tp)] == clean[k][max(0, s)] and s + To - 1 >= first[k]]
        # with read_images=False a sample names its frames (rows of policy.feature_cache's table) instead
        self.read_images = read_images
        self.frame_offset = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.num_frames = int(sum(self.lengths))
        H, W = cfg.image_size
        nbytes = self.num_frames * len(cfg.cameras) * H * W * 3
        self.images = None
        if max_cache_bytes is None:
            max_cache_bytes = 0.5 * available_memory()
        # without read_images only the feature table's one pass reads the frames: holding them all would cost
        # memory for nothing (2540 episodes: 31 GB, killed on a 23 GB machine)
        if read_images and nbytes <= max_cache_bytes:
            self.images = [{c: self._read(i, c, 0, None) for c in cfg.cameras} for i in self.episodes]

    def _language(self, embedder) -> None:
        """Embed every distinct instruction (and subtask label, if used) once."""
        metas = [self.store.meta(i) for i in self.episodes]
        self.instructions = [m["instruction"] for m in metas]
        self.subtask_labels = [list(m.get("subtasks") or []) for m in metas]
        texts = sorted(set(self.instructions) | ({t for labels in self.subtask_labels for t in labels}
                                                  if self.cfg.subtask_language_prob > 0 else set()))
        if embedder is None:
            from policy.text import default_embedder

            embedder = default_embedder()
        table = embed_instructions(embedder, texts, self.cfg.text_goal)
        if table.shape != (len(texts), self.cfg.text_input_dim):
            raise ValueError(f"embedder returned {table.shape}, expected ({len(texts)}, {self.cfg.text_input_dim})")
        self.text_row = {t: k for k, t in enumerate(texts)}
        self.text_table = torch.from_numpy(table)

    def _read(self, i: int, camera: str, start: int, stop: int | None) -> np.ndarray:
        frames = self.store.window(i, start, stop, fields=(f"{camera}_rgb",))[f"{camera}_rgb"]
        if frames.shape[1:3] != tuple(self.cfg.image_size):
            raise ValueError(f"episode {i} camera {camera}: images are {frames.shape[1:3]}, the config expects "
                             f"{tuple(self.cfg.image_size)}")
        return frames

    def episode_frames(self, k: int, camera: str, idx: np.ndarray) -> np.ndarray:
        """Frames idx of the k-th used episode's camera, (len(idx), H, W, 3) uint8 (from memory or the store)."""
        if self.images is not None:
            return self.images[k][camera][idx]
        lo, hi = int(idx.min()), int(idx.max()) + 1
        return self._read(self.episodes[k], camera, lo, hi)[idx - lo]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, item) -> dict:
        index, seed = item if isinstance(item, tuple) else (item, None)
        rng = np.random.default_rng(seed)
        k, s = self.index[index]
        cfg, T = self.cfg, self.lengths[k]
        obs = np.clip(np.arange(s, s + cfg.obs_horizon), 0, T - 1)
        act = np.clip(np.arange(s, s + cfg.pred_horizon), 0, T - 1)
        images, jitter = self._images(k, obs, rng) if self.read_images else (None, None)
        text = self.instructions[k]
        now = int(obs[-1])
        if self.train and cfg.subtask_language_prob > 0 and rng.random() < cfg.subtask_language_prob:
            j = int(self.subtask[k][now])
            if 0 <= j < len(self.subtask_labels[k]):
                text = self.subtask_labels[k][j]
        action = self.action[k][act]
        if cfg.action_frame == "tcp":
            action = self.normalizer.normalize_action(to_tcp(action, self.tcp_pose[k][now]))
        proprio = self.proprio[k][obs]
        if cfg.stage_bins:
            proprio = with_stage(proprio, int(self.stage[k][now]), cfg.stage_bins)
        out = {"proprio": torch.from_numpy(proprio), "aux": self.aux_target(index),
               "action": torch.from_numpy(action), "text": self.text_table[self.text_row[text]]}
        if not self.read_images:  # copy c of frame f is row c * num_frames + f; copy 0 is the unaugmented one
            copy = int(rng.integers(0, max(1, cfg.feature_cache))) if self.train else 0
            out["frames"] = torch.from_numpy(copy * self.num_frames + self.frame_offset[k] + obs)
            return out
        out["images"] = images
        if self.uint8_images:
            out["jitter"] = torch.from_numpy(jitter)
        return out

    def _images(self, k: int, obs: np.ndarray, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
        """A sample's images {camera: (To, 3, h, w)} (cropped; jittered unless uint8_images) and the jitter."""
        cfg = self.cfg
        images = {}
        jitter = jitter_factors(rng, cfg.color_jitter if self.train else 0.0)
        for camera in cfg.cameras:
            frames = self.episode_frames(k, camera, obs)
            if self.train:
                H, W = frames.shape[1:3]
                top, left = int(rng.integers(0, H - cfg.crop_size[0] + 1)), int(rng.integers(0, W - cfg.crop_size[1] + 1))
                frames = crop(frames, cfg.crop_size, top, left)
            else:
                frames = crop(frames, cfg.crop_size)
            # contiguous NCHW: the same memory layout (hence the same conv kernels, bit for bit) whether a
            # batch is collated here or in a DataLoader worker's shared memory
            x = torch.from_numpy(np.ascontiguousarray(frames.transpose(0, 3, 1, 2)))
            if not self.uint8_images:
                x = x.float() / 255.0
                x = color_jitter(x, torch.from_numpy(jitter)) if self.train else x
            images[camera] = x
        return images, jitter

    def task_of(self, index: int) -> str:
        """The task family of the episode sample `index` comes from."""
        return self.tasks[self.index[index][0]]

    def before_grasp(self, index: int) -> bool:
        """Whether the sample's newest observation comes before its episode closes the gripper: the frames on
        which the grasp point can be seen where it is (afterwards the object rides in the fingers)."""
        k, s = self.index[index]
        return s + self.cfg.obs_horizon - 1 < self.grasp_step[k]

    def _newest_step(self, index: int) -> tuple[int, int]:
        """(episode, step) of the sample's newest observation, clamped into the episode (windows reach past
        its ends)."""
        k, s = self.index[index]
        return k, min(max(s + self.cfg.obs_horizon - 1, 0), self.lengths[k] - 1)

    def grasp_ahead(self, index: int) -> tuple[int, bool]:
        """Which grasp of its episode (0: the first) the sample's newest observation heads for or is in, and
        whether it still comes before it: a long task grasps more than once (drawer_put: the handle, the
        object, the handle again), and the frames on the way to a later grasp show that grasp's point."""
        k, now = self._newest_step(index)
        ahead = int(self.cycle[k][now, 0])
        return int(np.searchsorted(np.unique(self.cycle[k][:, 0]), ahead)), now < ahead

    def carrying(self, index: int) -> bool:
        """Whether the sample's newest observation falls between its episode's grasp and release: the frames
        on which the policy carries the object and aims for the release point."""
        k, s = self.index[index]
        return self.grasp_step[k] <= s + self.cfg.obs_horizon - 1 < self.release_step[k]

    def aux_target(self, index: int) -> torch.Tensor:
        """The sample's auxiliary target (cfg.aux_dim,) in the config's `aux_target_frame`, without reading
        images: the grasp and release points, then with aux_grasp_axis the axis (policy.grasp_axis)."""
        k, now = self._newest_step(index)
        if self.cfg.aux_target_frame == "tcp":
            points = aux_point_target(self.aux_points[k][now], self.tcp_pose[k][now], self.cfg.aux_release_frame)
            if not self.cfg.aux_grasp_axis:
                return points
            axis = axis_label(self.grasp_yaw[k][now], yaw_of(self.tcp_pose[k][now, 3:9]), self.has_axis[k])
            return torch.cat([points, torch.from_numpy(axis)])
        return grasp_and_release(self.action[k], tuple(self.cycle[k][now]))

    def info(self) -> dict:
        """What the run records about its data (copied into the bundle manifest)."""
        metas = [self.store.meta(i) for i in self.episodes]
        return {"content_hash": self.store.content_hash(), "path": str(self.store.root),
                "episodes_total": len(self.store), "episodes_used": len(self.episodes),
                "include_failures": self.include_failures, "steps_used": int(sum(self.lengths)), "samples": len(self),
                "tasks": sorted({m["task"] for m in metas}), "instructions": sorted(set(self.instructions)),
                "texts": sorted(self.text_row), "holdout": data_holdout(metas),
                "gripper_levels": list(self.gripper_levels)}
