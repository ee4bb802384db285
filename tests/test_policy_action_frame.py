"""Gripper-relative actions (policy.action_frame): the maths, the training samples and the bundle's output."""

import numpy as np
import pytest

from datagen.schema import rot6d, rot6d_to_matrix
from policy.action_frame import from_tcp, relative_windows, to_tcp, window_indices
from runtime.bench_runtime import test_cache_dir as cache_dir


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _pose(p, R) -> np.ndarray:
    return np.concatenate([p, rot6d(R)])


def _actions(rng, n: int) -> np.ndarray:
    a = np.zeros((n, 10), np.float32)
    a[:, :3] = rng.uniform(-0.5, 0.5, (n, 3))
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        a[i, 3:9] = rot6d(q * np.sign(np.linalg.det(q)))
    a[:, 9] = rng.uniform(0, 1, n)
    return a


def test_a_point_ahead_of_a_turned_gripper_reads_as_ahead():
    # gripper at (0.4, 0, 0.3) turned 90 deg about z: its x axis points along base +y
    pose = _pose([0.4, 0.0, 0.3], _rz(90))
    target = np.concatenate([[0.4, 0.1, 0.3], rot6d(_rz(90)), [1.0]])[None]
    rel = to_tcp(target, pose)
    np.testing.assert_allclose(rel[0, :3], [0.1, 0.0, 0.0], atol=1e-6)  # 10 cm along the gripper's own x
    np.testing.assert_allclose(rel[0, 3:9], rot6d(np.eye(3)), atol=1e-6)  # same orientation: identity
    assert rel[0, 9] == 1.0  # the gripper command is not a pose: unchanged


def test_to_and_from_the_gripper_frame_round_trip():
    rng = np.random.default_rng(0)
    a, pose = _actions(rng, 16), _actions(rng, 1)[0, :9]
    back = from_tcp(to_tcp(a, pose), pose)
    np.testing.assert_allclose(back, a, atol=1e-5)
    # the pose itself is the origin of its own frame
    me = np.concatenate([pose, [0.0]])[None]
    np.testing.assert_allclose(to_tcp(me, pose)[0, :9], np.r_[0, 0, 0, rot6d(np.eye(3))], atol=1e-6)
    # distances survive (a rigid change of frame): what a metre means does not depend on the frame
    rel = to_tcp(a, pose)
    np.testing.assert_allclose(np.linalg.norm(rel[1:, :3] - rel[:-1, :3], axis=1),
                               np.linalg.norm(a[1:, :3] - a[:-1, :3], axis=1), atol=1e-5)


def test_batched_poses_give_each_chunk_its_own_frame():
    rng = np.random.default_rng(1)
    chunks, poses = np.stack([_actions(rng, 4) for _ in range(3)]), _actions(rng, 3)[:, :9]
    together = to_tcp(chunks, poses)
    for i in range(3):
        np.testing.assert_allclose(together[i], to_tcp(chunks[i], poses[i]), atol=1e-6)


def test_window_indices_clamp_like_the_sampler():
    now, steps = window_indices(5, obs_horizon=2, pred_horizon=4)
    assert now.tolist() == [0, 1, 2, 3, 4]
    assert steps[0].tolist() == [0, 0, 1, 2]  # the first step repeats before the start
    assert steps[4].tolist() == [3, 4, 4, 4]  # the last one after the end
    rng = np.random.default_rng(2)
    a, p = _actions(rng, 5), np.hstack([_actions(rng, 5)[:, :9], np.zeros((5, 7))])
    rel = relative_windows(a, p, 2, 4).reshape(5, 4, 10)
    np.testing.assert_allclose(rel[3], to_tcp(a[steps[3]], p[3, :9]), atol=1e-6)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    from policy.testing import synthetic_dataset

    # smooth: valid rotations (the i.i.d. random episodes' rot6d are not rotations, which no frame maps back)
    return synthetic_dataset(tmp_path_factory.mktemp("frame") / "data", episodes=4, smooth=True)


def test_tcp_frame_samples_are_the_recorded_targets_seen_from_the_newest_pose(data_dir):
    import torch

    from datagen.store import Dataset
    from policy.config import load_policy_config
    from policy.data import PolicyDataset
    from policy.testing import TINY, hash_embedder

    cfg = load_policy_config(TINY, {"action_frame": "tcp", "aux_target_weight": 1.0, "aux_target_frame": "tcp"})
    ds = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder)
    raw = Dataset(data_dir)
    for index in (0, 7, len(ds) - 1):
        k, s = ds.index[index]
        arrays = raw.window(ds.episodes[k], fields=("proprio", "action"))
        T = len(arrays["action"])
        now = int(np.clip(s + cfg.obs_horizon - 1, 0, T - 1))
        steps = np.clip(np.arange(s, s + cfg.pred_horizon), 0, T - 1)
        got = ds.normalizer.unnormalize_action(ds[index]["action"].numpy())
        np.testing.assert_allclose(from_tcp(got, arrays["proprio"][now, :9]), arrays["action"][steps], atol=1e-4)
    every = torch.stack([ds[i]["action"] for i in range(len(ds))])
    assert every.min() >= -1.0 - 1e-5 and every.max() <= 1.0 + 1e-5  # stats fitted on the relative chunks


def test_tcp_frame_needs_a_tcp_frame_aux_target():
    from policy.config import ConfigError, load_policy_config
    from policy.testing import TINY

    with pytest.raises(ConfigError, match="aux_target_frame"):
        load_policy_config(TINY, {"action_frame": "tcp", "aux_target_weight": 1.0, "aux_target_frame": "base"})
    assert load_policy_config(TINY, {"action_frame": "tcp"}).action_frame == "tcp"  # no aux: nothing to clash


def test_rot6d_helpers_agree_with_the_schema():
    from policy.action_frame import rotations

    rng = np.random.default_rng(3)
    d6 = rng.normal(size=6)
    np.testing.assert_allclose(rotations(d6), rot6d_to_matrix(d6), atol=1e-12)


def test_a_tcp_frame_bundle_hands_the_runtime_absolute_targets(tmp_path, data_dir):
    import json
        
    from policy.bundle import Bundle
    from policy.export import export
    from policy.testing import TINY, hash_embedder
    from policy.train import train

    overrides = {"action_frame": "tcp", "aux_target_weight": 1.0, "aux_target_frame": "tcp"}
    train(data_dir, dict(TINY), tmp_path / "run", steps=4, embedder=hash_embedder, progress=False, threads=1,
          overrides=overrides)
    cache = cache_dir()
    export(tmp_path / "run", tmp_path / "bundle", cache_dir=cache)  # its parity check composes both sides
    m = json.loads((tmp_path / "bundle" / "manifest.json").read_text())
    assert m["action_layout"]["frame"] == "tcp" and m["parity"]["chunk_max_abs_err"] <= 1e-4
    b = Bundle.load(tmp_path / "bundle")
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 255, (2, 32, 32, 3), dtype=np.uint8) for c in b.cameras}
    proprio = np.zeros((2, 16), np.float32)
    proprio[:, :3], proprio[:, 3:9] = [0.4, 0.1, 0.3], rot6d(_rz(30) @ np.diag([1.0, -1.0, -1.0]))
    noise = rng.normal(size=(b.pred_horizon, b.action_dim)).astype(np.float32)
    chunk = b.act(images, proprio, b.embed("do pick_place"), noise=noise)
    b.action_frame = "base"  # the same network output, read as if it were absolute
    relative = b.act(images, proprio, b.embed("do pick_place"), noise=noise)
    np.testing.assert_allclose(chunk, from_tcp(relative, proprio[-1, :9]), atol=1e-5)
    assert np.abs(chunk[:, :3] - relative[:, :3]).max() > 0.05  # the composition did move it
