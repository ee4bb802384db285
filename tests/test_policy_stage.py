"""Grasp cycles as a policy input (policy.stage): the count, the training samples, the bundle, the warm start."""

from __future__ import annotations

import numpy as np
import pytest

from policy.stage import GraspCycles, commands_in_effect, cycles_per_step, one_hot, with_stage


def _feed(pairs) -> list[int]:
    c = GraspCycles()
    return [c.update(cmd, pos) for cmd, pos in pairs]


def test_a_hold_counts_once_it_is_let_go():
    # open, closing on a block (fingers stop at 0.5), carried, let go
    seq = [(0, 0)] * 2 + [(1, 0.3), (1, 0.5), (1, 0.5)] + [(0, 0.3), (0, 0.0)]
    assert _feed(seq) == [0, 0, 0, 0, 0, 1, 1]


def test_a_let_go_counts_once_the_fingers_open_not_while_they_still_hold():
    # a wide object (held at 0.49) under the 0.5 level the channel passes through on its way down: still held
    wide = [(1, 0.3), (1, 0.49), (0.5, 0.49), (0.5, 0.47), (0.5, 0.43), (0.0, 0.2), (0.0, 0.0)]
    assert _feed(wide) == [0, 0, 0, 0, 1, 1, 1]
    # and a close again before the fingers opened is the same hold
    assert _feed([(1, 0.49), (0.5, 0.49), (1, 0.49), (0, 0.1)]) == [0, 0, 0, 1]
    # a narrower object dropped at the 0.5 level (fingers 0.55 -> 0.52), then a close on nothing: it was let go
    assert _feed([(1, 0.55), (0.5, 0.52), (1, 0.7), (1, 0.98), (0, 0.1), (1, 0.98), (0, 0.1)]) == [0, 0, 0, 1, 1, 1, 1]


def test_a_missed_grasp_and_the_half_open_pre_shape_do_not_count():
    air = [(1, 0.6), (1, 0.99), (0, 0.4), (0, 0.0)]  # closed on nothing, reopened to retry
    pre_shape = [(0.5, 0.3), (0.5, 0.5), (0.0, 0.1)]  # the handle's half-open approach
    assert _feed(air + pre_shape) == [0] * 7
    assert _feed(air + [(1, 0.85), (1, 0.86), (0, 0.2)]) == [0, 0, 0, 0, 0, 0, 1]  # the retry holds the handle


def test_a_slow_let_go_that_hovers_at_the_threshold_counts_once():
    # step 29's drawer_put seed 100517: the policy's channel came down 0.85, 0.7499, 0.7501, 0.66 on the handle
    slow = [(1, 0.85), (1, 0.84), (0.85, 0.85), (0.7499, 0.73), (0.7501, 0.77), (0.66, 0.72), (0.5, 0.6), (0.0, 0.1)]
    assert _feed(slow) == [0, 0, 0, 0, 0, 0, 1, 1]
    # inside the band nothing changes: a close that comes back up from 0.65 is the same hold
    assert _feed([(1, 0.5), (0.65, 0.5), (1, 0.5), (0.2, 0.3)]) == [0, 0, 0, 1]


def test_reset_starts_a_new_task_and_bad_numbers_are_refused():
    c = GraspCycles()
    for cmd, pos in [(1, 0.5), (0, 0.1)]:
        c.update(cmd, pos)
    assert c.count == 1
    c.reset()
    assert c.count == 0 and c.update(0, 0) == 0
    with pytest.raises(ValueError, match="finite"):
        c.update(float("nan"), 0.2)


def test_one_hot_and_the_last_class_holds_the_rest():
    assert one_hot(0, 3).tolist() == [1, 0, 0]
    assert one_hot(5, 3).tolist() == [0, 0, 1]
    with pytest.raises(ValueError):
        one_hot(-1, 3)
    p = np.zeros((2, 16), np.float32)
    assert with_stage(p, 1, 0).shape == (2, 16)
    assert with_stage(p, 1, 3)[:, 16:].tolist() == [[0, 1, 0], [0, 1, 0]]


def test_the_collectors_drawer_put_counts_one_cycle_per_finished_grasp():
    """On a recorded episode: 0 while opening the drawer, 1 while taking the object, 2 while closing it."""
    from datagen.episode import DatagenConfig, run_episode

    ep = run_episode("drawer_put", 0, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    cycles = cycles_per_step(commands_in_effect(ep.action), ep.proprio[:, 9])
    starts = [0, *(np.flatnonzero(np.diff(ep.subtask)) + 1)]
    assert [(int(ep.subtask[i]), int(cycles[i])) for i in starts] == [(0, 0), (1, 1), (2, 1), (3, 2)]
    assert np.all(np.diff(cycles) >= 0)


def _cycling_dataset(root):
    """Synthetic episodes whose gripper holds something twice (closure 0.5 under a closed command)."""
    from datagen.store import ShardWriter
    from datagen.workers import synthetic_episode
    from policy.testing import smooth_episode

    with ShardWriter(root, "w0") as w:
        for seed in range(4):
            ep = synthetic_episode("pick_place", seed, size=32)
            smooth_episode(ep, seed)
            T = len(ep)
            cmd = np.zeros(T, np.float32)
            cmd[T // 10:2 * T // 10] = 1.0
            cmd[3 * T // 10:4 * T // 10] = 1.0
            ep.proprio[:, 9] = 0.5 * cmd
            ep.action[:, 9] = np.concatenate([cmd[1:], cmd[-1:]])  # the target of the next step
            ep.meta["success"] = ep.meta["label"]["success"] = True
            w.append(ep)
    return root


def test_training_samples_carry_the_newest_steps_stage(tmp_path):
    from policy.config import load_policy_config
    from policy.data import PolicyDataset
    from policy.testing import TINY, hash_embedder

    data = _cycling_dataset(tmp_path / "data")
    cfg = load_policy_config(None, {**TINY, "stage_bins": 3})
    ds = PolicyDataset(data, cfg, train=False, embedder=hash_embedder)
    seen = set()
    for i in range(len(ds)):
        k, s = ds.index[i]
        x = ds[i]["proprio"].numpy()
        assert x.shape == (cfg.obs_horizon, 16 + 3)
        now = min(max(s + cfg.obs_horizon - 1, 0), ds.lengths[k] - 1)
        assert np.argmax(x[-1, 16:]) == ds.stage[k][now] and np.all(x[0, 16:] == x[-1, 16:])
        seen.add(int(ds.stage[k][now]))
    assert seen == {0, 1, 2}


@pytest.fixture(scope="module")
def stage_bundle(tmp_path_factory):
    """A TINY run without the stage, then a run that adds it by warm start, exported (parity checked there)."""
    from policy.export import export
    from policy.testing import TINY, hash_embedder, tiny_run
    from policy.train import train

    root = tmp_path_factory.mktemp("stage")
    base = tiny_run(root / "base")
    data = _cycling_dataset(root / "data")
    train(data, {**TINY, "stage_bins": 3}, root / "run", steps=4, embedder=hash_embedder, progress=False,
          threads=1, init_from=base)
    export(root / "run", root / "bundle")
    return base, root / "run", root / "bundle"


def test_a_warm_start_adds_the_stage_without_changing_what_the_policy_does(stage_bundle):
    import torch

    from policy.config import load_policy_config
    from policy.model import DiffusionPolicy
    from policy.testing import TINY
    from policy.warm_start import load_into

    base, _, _ = stage_bundle
    model = DiffusionPolicy(load_policy_config(None, {**TINY, "stage_bins": 3})).eval()
    record = load_into(model, base)
    assert any(g.startswith("obs_encoder.proprio.0.weight") for g in record["grown"]), record
    g = torch.Generator().manual_seed(0)
    images = {c: torch.rand(1, 2, 3, 28, 28, generator=g) for c in model.cfg.cameras}
    p, text = torch.randn(1, 2, 16, generator=g), torch.randn(1, 384, generator=g)
    conds = [model.encode(images, torch.from_numpy(with_stage(p.numpy(), k, 3)), text) for k in (0, 1, 2)]
    assert torch.equal(conds[0], conds[1]) and torch.equal(conds[0], conds[2])


def test_the_bundle_reads_the_stage_and_an_older_bundle_ignores_it(stage_bundle, tmp_path):
    import json

    from policy.bundle import Bundle
    from policy.export import export

    base, _, bundle_dir = stage_bundle
    m = json.loads((bundle_dir / "manifest.json").read_text())
    assert m["dims"]["stage_bins"] == 3 and m["dims"]["proprio"] == 16
    proprio_in = next(i for i in m["graphs"]["obs_encoder"]["inputs"] if i["name"] == "proprio")
    assert proprio_in["shape"][-1] == 19 and m["parity"]["chunk_max_abs_err"] <= 1e-3
    b = Bundle.load(bundle_dir)
    assert b.info()["stage_bins"] == 3
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8) for c in b.cameras}
    proprio = rng.uniform(-0.1, 0.1, (2, 16)).astype(np.float32)
    noise = rng.normal(size=(b.pred_horizon, b.action_dim)).astype(np.float32)
    text = b.embed("pick up the red block")
    chunks = [b.act(images, proprio, text, noise=noise, stage=k) for k in (0, 1, 2, 7)]
    assert not np.allclose(chunks[0], chunks[1]) and not np.allclose(chunks[1], chunks[2])
    assert np.array_equal(chunks[2], chunks[3])  # 7 cycles fall in the last class, "2 or more"
    export(base, tmp_path / "old")
    old = Bundle.load(tmp_path / "old")
    assert old.stage_bins == 0
    assert np.array_equal(old.act(images, proprio, text, noise=noise, stage=0),
                          old.act(images, proprio, text, noise=noise, stage=2))


def test_pretraining_refuses_the_stage(tmp_path):
    from policy.pretrain import pretrain
    from policy.testing import TINY

    with pytest.raises(ValueError, match="stage_bins 3"):
        pretrain(tmp_path / "views", tmp_path / "data", {**TINY, "stage_bins": 3, "aux_target_weight": 1.0,
                                                         "aux_target_frame": "tcp"}, tmp_path / "out", steps=1)
