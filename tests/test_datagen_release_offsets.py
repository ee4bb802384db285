"""Where the placed object sat in the hand at its release (datagen/release_offsets.py), and the release point
the policy learns from it (policy config `release_point`)."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.episode import DatagenConfig, run_episode
from datagen.release_offsets import release_offset_at
from datagen.schema import grasp_and_release_per_step
from policy.config import ConfigError, PolicyConfig, load_policy_config
from policy.data import object_release_points


@pytest.fixture(scope="module")
def off_centre_stack():
    # seed 1 at 2 cm of grasp noise: the grasp closed ~2 cm off the block's centre (found by running seeds 0-5)
    return run_episode("stack", 1, DatagenConfig(dr="light", max_retries=2, grasp_noise_cm=2.0))


def _target_xy(ep) -> np.ndarray:
    objects = {o["name"]: o["placement"] for o in ep.meta["task_record"]["objects"]}
    target = objects[ep.meta["plan"]["subtasks"][1]["args"]["target"]]
    return np.array([target["x"], target["y"]])


def test_each_place_records_the_objects_offset_at_the_schemas_release_step(off_centre_stack):
    ep = off_centre_stack
    assert ep.meta["success"]
    records = ep.meta["release_offsets"]
    assert [r["object"] for r in records] == [ep.meta["plan"]["subtasks"][1]["args"]["object"]]
    releases = set(grasp_and_release_per_step(ep.action, ep.subtask)[:, 1].tolist())
    step = records[0]["step"]
    assert step in releases
    assert ep.action[step, 9] < 0.5 <= ep.action[step - 1, 9], "the first action with the fingers told to open"


def test_the_tcp_let_go_beside_the_block_below_and_the_offset_says_where_the_object_went(off_centre_stack):
    ep = off_centre_stack
    r = ep.meta["release_offsets"][0]
    tcp = ep.action[r["step"], :2].astype(np.float64)
    target = _target_xy(ep)
    assert np.linalg.norm(tcp - target) > 0.015, "an off-centre grasp: the TCP lets go beside the target"
    assert np.linalg.norm(tcp + np.asarray(r["offset_m"][:2]) - target) < 0.005


def test_object_release_points_move_only_the_recorded_release_and_only_horizontally(off_centre_stack):
    ep = off_centre_stack
    cycle = grasp_and_release_per_step(ep.action, ep.subtask)
    points = ep.action[cycle, :3]
    moved = object_release_points(points, cycle, ep.meta["release_offsets"])
    r = ep.meta["release_offsets"][0]
    on_it = cycle[:, 1] == r["step"]
    assert on_it.any()
    assert np.allclose(moved[on_it, 1, :2] - points[on_it, 1, :2], np.asarray(r["offset_m"][:2]), atol=1e-6)
    assert np.allclose(moved[:, 0], points[:, 0]) and np.allclose(moved[:, 1, 2], points[:, 1, 2])
    assert np.allclose(moved[~on_it], points[~on_it])
    # older data, or a release no place made (a drawer handle let go): the TCP's point stays
    assert np.array_equal(object_release_points(points, cycle, None), points.astype(np.float64))
    far = [dict(r, step=r["step"] + 10)]
    assert np.array_equal(object_release_points(points, cycle, far), points.astype(np.float64))


def test_release_offset_lookup_takes_the_nearest_within_tolerance():
    records = [{"step": 10, "object": "a", "offset_m": [0.01, 0.0, 0.0]},
               {"step": 40, "object": "a", "offset_m": [0.0, 0.02, 0.0]}]
    assert release_offset_at(records, 41)[1] == pytest.approx(0.02)
    assert release_offset_at(records, 12)[0] == pytest.approx(0.01)
    assert release_offset_at(records, 25) is None and release_offset_at([], 10) is None


def test_release_point_object_needs_the_gripper_frame_aux_target():
    with pytest.raises(ConfigError, match="release_point 'object' needs"):
        PolicyConfig(release_point="object", aux_target_frame="base").validate()
    with pytest.raises(ConfigError, match="release_point = 'hand' is not allowed"):
        load_policy_config("small", {"release_point": "hand"})


def test_the_policys_base_frame_release_target_is_where_the_object_went(tmp_path):
    from datagen.store import ShardWriter
    from datagen.workers import synthetic_episode
    from policy.config import AUX_TCP_SCALE
    from policy.data import PolicyDataset
    from policy.testing import TINY, hash_embedder

    ep = synthetic_episode("stack", 0, steps=40)
    grip = np.zeros(40, np.float32)
    grip[12:30] = 1.0  # a grasp at 12 let go at 30
    ep.action[:, -1] = grip
    ep.meta.update(success=True, label={"value": True, "source": "synthetic"},
                   release_offsets=[{"step": 30, "object": "obj0", "offset_m": [0.02, -0.01, -0.01]}])
    with ShardWriter(tmp_path / "d", "w0") as w:
        w.append(ep)
    aux = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "aux_release_frame": "base"}
    tcp = PolicyDataset(tmp_path / "d", load_policy_config(TINY, aux), train=False, embedder=hash_embedder)
    obj = PolicyDataset(tmp_path / "d", load_policy_config(TINY, {**aux, "release_point": "object"}), train=False,
                        embedder=hash_embedder)
    for index in (0, 10, len(tcp) - 1):
        shift = (obj.aux_target(index) - tcp.aux_target(index)).numpy() * AUX_TCP_SCALE
        np.testing.assert_allclose(shift, [0, 0, 0, 0.02, -0.01, 0], atol=1e-6)


def test_grasp_noise_episodes_can_train_from_their_settled_hold_on_only(tmp_path):
    from datagen.store import ShardWriter
    from datagen.workers import synthetic_episode
    from policy.data import HOLD_SETTLE_STEPS, PolicyDataset
    from policy.testing import TINY, hash_embedder

    def episode(seed, noisy):
        ep = synthetic_episode("stack", seed, steps=40)
        grip = np.zeros(40, np.float32)
        grip[12:30] = 1.0  # closes at 12, lets go at 30
        ep.action[:, -1] = grip
        ep.meta.update(success=True, label={"value": True, "source": "synthetic"})
        if noisy:
            ep.meta["grasp_noise_cm"] = 2.0
        return ep

    with ShardWriter(tmp_path / "d", "w0") as w:
        w.append(episode(0, noisy=True))
        w.append(episode(1, noisy=False))
    every = PolicyDataset(tmp_path / "d", load_policy_config(TINY), train=False, embedder=hash_embedder)
    held = PolicyDataset(tmp_path / "d", load_policy_config(TINY, {"grasp_noise_windows": "after_grasp"}),
                         train=False, embedder=hash_embedder)
    To = every.cfg.obs_horizon
    noisy = next(k for k, i in enumerate(held.episodes) if held.store.meta(i).get("grasp_noise_cm"))
    newest = [s + To - 1 for k, s in held.index if k == noisy]
    assert min(newest) == 12 + HOLD_SETTLE_STEPS
    assert newest == [s + To - 1 for k, s in every.index if k == noisy and s + To - 1 >= 12 + HOLD_SETTLE_STEPS]
    # the episode without grasp noise keeps every window
    assert [w for w in held.index if w[0] != noisy] == [w for w in every.index if w[0] != noisy]


def test_the_hold_the_windows_wait_for_is_the_collectors():
    from datagen.primitives import GRASP_SECONDS
    from datagen.schema import CONTROL_HZ
    from policy.data import HOLD_SETTLE_STEPS

    assert HOLD_SETTLE_STEPS == round(GRASP_SECONDS * CONTROL_HZ)
