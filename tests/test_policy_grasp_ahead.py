"""A task that grasps more than once (drawer_put: the handle, the object, the handle again): the samples say
which grasp they are on their way to (PolicyDataset.grasp_ahead), and validation reports the aux head's grasp
point on the way to each later grasp (val_grasp<i>_cm), where a head that keeps pointing at the first fails."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datagen.store import ShardWriter
from datagen.workers import synthetic_episode
from policy.config import load_policy_config
from policy.data import PolicyDataset, finish_images
from policy.model import DiffusionPolicy
from policy.testing import TINY, hash_embedder, smooth_episode
from policy.validate import Validator

T = 40
CLOSED = ((8, 14), (22, 30))  # two closed runs of the gripper command: grasps at steps 8 and 22


def _two_grasp_data(root, episodes: int = 6):
    with ShardWriter(root, "w0") as w:
        for seed in range(episodes):
            ep = synthetic_episode("drawer_put", seed, steps=T, size=32)
            smooth_episode(ep, seed)
            ep.action[:, -1] = 0.0
            for a, b in CLOSED:
                ep.action[a:b, -1] = 1.0
            ep.meta["success"] = True
            w.append(ep)
    return root


def test_samples_know_which_grasp_they_head_for_and_validation_reports_the_later_ones(tmp_path):
    cfg = load_policy_config(TINY, {"val_fraction": 0.5, "aux_target_weight": 1.0})
    data = _two_grasp_data(tmp_path / "data")
    kw = dict(train=False, embedder=hash_embedder)
    val = PolicyDataset(data, cfg, split="val", **kw)
    fit = PolicyDataset(data, cfg, split="train", normalizer=val.normalizer, **kw)
    assert len(val.episodes) and len(fit.episodes)
    now_of = {}
    for i in range(len(val)):
        k, s = val.index[i]
        now_of[i] = min(max(s + cfg.obs_horizon - 1, 0), T - 1)
    want = {i: (0, now < 8) if now < 14 else (1, now < 22) for i, now in now_of.items()}
    assert {i: val.grasp_ahead(i) for i in now_of} == want
    assert any(g == 1 and before for g, before in want.values())  # frames on the way to the second grasp exist

    check = Validator(val, fit, samples=len(val), batch=16)
    model = DiffusionPolicy(cfg)
    got = check(model, torch.device("cpu"))
    assert "val_grasp1_cm" in got and "val_grasp2_cm" not in got and "fit_grasp1_cm" not in got
    # the median of the head's grasp-point miss over exactly the samples on their way to the second grasp
    ds, idx = check.sets["val"]
    on_way = [int(i) for i in idx if ds.grasp_ahead(int(i)) == (1, True)]
    with torch.no_grad():
        b = torch.utils.data.default_collate([ds[i] for i in on_way])
        b = finish_images(b) if ds.uint8_images else b
        pred = model.eval().aux_points(model.obs_encoder(b["images"], b["proprio"], b["text"]))[:, :3].numpy()
    miss = np.linalg.norm(check._metres(pred) - check._metres(b["aux"][:, :3].numpy()), axis=1) * 100
    assert got["val_grasp1_cm"] == pytest.approx(float(np.median(miss)), rel=1e-5)
