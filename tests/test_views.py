"""Rendered views for encoder pretraining (datagen.views) and the pretraining itself (policy.pretrain)."""

import json

import numpy as np
import pytest
import torch

from datagen.views import generate, load, measure_offsets, sample_pose, scene_views
from sim.build import build_episode
from sim.state import StateView

OFFSETS = {"grasp": np.array([0.0, 0.0, 0.01]), "release": np.array([0.0, 0.0, 0.06])}
SIZE = (32, 32)


@pytest.fixture(scope="module")
def views_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("views")
    generate(out, range(300, 302), 3, OFFSETS, progress=False, image_size=SIZE)
    return out


def test_a_scene_view_is_labelled_with_the_named_objects_and_bins_positions():
    v = scene_views(300, 3, OFFSETS, image_size=SIZE)
    ep = build_episode("pick_place", 300, "heavy", "fast")
    state = StateView(ep.world)
    want = [state.position(ep.instance.params["target"]) + OFFSETS["grasp"],
            state.position(ep.instance.params["bin"]) + OFFSETS["release"]]
    np.testing.assert_allclose(v["points"], np.broadcast_to(want, (3, 2, 3)), atol=1e-6)
    assert v["instruction"] == [ep.instruction] * 3 and v["scene"].shape == (3, 32, 32, 3)
    np.testing.assert_allclose(v["proprio"][0, :3], ep.world.tcp_pose()[:3, 3], atol=1e-6)  # first view: home
    assert np.linalg.norm(v["proprio"][1:, :3] - v["proprio"][0, :3], axis=1).min() > 0.01  # the others moved
    again = scene_views(300, 3, OFFSETS, image_size=SIZE)
    assert all(np.array_equal(v[k], again[k]) for k in ("scene", "wrist", "proprio"))


def test_sampled_poses_head_for_the_object_and_point_down():
    rng = np.random.default_rng(0)
    home = np.eye(4)
    home[:3, :3], home[:3, 3] = np.diag([1.0, -1.0, -1.0]), [-0.13, 0.49, 0.33]
    grasp = np.array([0.1, 0.35, 0.03])
    poses = [sample_pose(home, grasp, 0.4, rng) for _ in range(300)]
    p = np.array([T[:3, 3] for T in poses])
    assert p[:, 2].min() >= grasp[2]
    assert np.median(np.linalg.norm(p - grasp, axis=1)) < np.linalg.norm(home[:3, 3] - grasp)
    assert min(T[2, 2] for T in poses) < -0.95  # the tool z axis stays near straight down


def test_shards_are_written_whole_and_a_rerun_keeps_them(views_dir):
    shards = sorted(views_dir.glob("*.npz"))
    assert [p.name for p in shards] == ["views_pick_place_00000300.npz"]
    before = shards[0].stat().st_mtime_ns
    generate(views_dir, range(300, 302), 3, OFFSETS, progress=False, image_size=SIZE)
    assert shards[0].stat().st_mtime_ns == before
    v = load(views_dir)
    assert len(v["proprio"]) == 6 and sorted(set(v["seed"].tolist())) == [300, 301]


def test_views_are_relabelled_for_the_offsets_of_another_dataset(views_dir):
    other = {"grasp": OFFSETS["grasp"] + [0.01, 0.0, 0.0], "release": OFFSETS["release"] + [0.0, 0.0, 0.05]}
    a, b = load(views_dir), load(views_dir, {"pick_place": other})
    np.testing.assert_allclose(b["points"] - a["points"],
                               np.broadcast_to([[0.01, 0.0, 0.0], [0.0, 0.0, 0.05]], a["points"].shape), atol=1e-6)
    assert np.array_equal(a["scene"], b["scene"]) and b["points"].dtype == a["points"].dtype


def test_pretraining_fits_the_views_and_a_policy_run_starts_from_it(views_dir, tmp_path):
    from policy import warm_start
    from policy.config import load_policy_config
    from policy.model import DiffusionPolicy
    from policy.pretrain import pretrain
    from policy.testing import TINY, hash_embedder, synthetic_dataset

    data = synthetic_dataset(tmp_path / "data", episodes=4, smooth=True)
    over = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "lr": 3e-3,
            "warmup_steps": 1, "log_every": 5, "color_jitter": 0.0}
    s = pretrain(views_dir, data, dict(TINY), tmp_path / "pre", 60, over, threads=1, progress=False,
                 embedder=hash_embedder)
    rows = [json.loads(x) for x in (tmp_path / "pre" / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in rows if "loss" in r]
    assert s["views"] == 6 and losses[-1] < 0.5 * losses[0]
    model = DiffusionPolicy(load_policy_config(TINY, {**over, "aux_condition": True}))
    warm_start.load_into(model, tmp_path / "pre")
    saved = torch.load(s["checkpoint"], weights_only=False)["ema"]["model"]
    torch.testing.assert_close(model.aux_head[0].weight, saved["aux_head.0.weight"])
    # only the pretrained parts come over, so another observation horizon (another cond width) starts from it
    short = DiffusionPolicy(load_policy_config(TINY, {**over, "obs_horizon": 1}))
    record = warm_start.load_into(short, tmp_path / "pre")
    name = "obs_encoder.images.scene.stem.0.weight"
    torch.testing.assert_close(short.state_dict()[name], saved[name])
    assert not record["grown"] and all(k.startswith(("unet.", "obs_encoder.proprio", "obs_encoder.text"))
                                       for k in record["new"])
    from policy.train import train

    train(data, dict(TINY), tmp_path / "policy", steps=1, embedder=hash_embedder, progress=False, threads=1)
    with pytest.raises(FileExistsError, match="holds a policy run"):
        pretrain(views_dir, data, dict(TINY), tmp_path / "policy", 1, over, threads=1, progress=False,
                 embedder=hash_embedder)
    with pytest.raises(ValueError, match="views are"):
        pretrain(views_dir, data, dict(TINY, image_size=[64, 64], crop_size=[56, 56]), tmp_path / "bad", 1, over,
                 threads=1, progress=False, embedder=hash_embedder)


def test_pretraining_goes_on_from_an_earlier_pretraining_run_only(views_dir, tmp_path):
    from policy.pretrain import pretrain
    from policy.testing import TINY, hash_embedder, synthetic_dataset

    data = synthetic_dataset(tmp_path / "data", episodes=4, smooth=True)
    over = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "lr": 3e-3, "warmup_steps": 1, "log_every": 5,
            "color_jitter": 0.0}

    def run(out, steps, lr, **kw):
        s = pretrain(views_dir, data, dict(TINY), out, steps, {**over, "lr": lr}, threads=1, progress=False,
                     embedder=hash_embedder, **kw)
        return torch.load(s["checkpoint"], weights_only=False)["ema"]["model"], s

    name = "obs_encoder.images.scene.stem.0.weight"
    first, _ = run(tmp_path / "pre", 20, 3e-3)
    # with a vanishing learning rate a run keeps the weights it starts from: the earlier run's, not new ones
    kept, on = run(tmp_path / "on", 2, 1e-12, init_from=tmp_path / "pre")
    fresh, _ = run(tmp_path / "fresh", 2, 1e-12)
    torch.testing.assert_close(kept[name], first[name])
    torch.testing.assert_close(kept["aux_head.0.weight"], first["aux_head.0.weight"])
    assert not torch.allclose(fresh[name], first[name])
    assert on["init_from"] == str(tmp_path / "pre")
    assert json.loads((tmp_path / "on" / "warm_start.json").read_text())["step"] == 20
    # the labels were moved to the offsets measured on --data, and the run says which
    measured = measure_offsets(data)
    said = json.loads((tmp_path / "on" / "dataset.json").read_text())["pretrain"]["offsets_m"]["pick_place"]
    np.testing.assert_allclose(said["release"], measured["release"], atol=1e-4)
    (tmp_path / "pre" / "dataset.json").write_text("{}")
    with pytest.raises(ValueError, match="neither a `sudd pretrain` run"):
        pretrain(views_dir, data, dict(TINY), tmp_path / "bad", 1, over, threads=1, progress=False,
                 embedder=hash_embedder, init_from=tmp_path / "pre")


def test_head_only_pretraining_trains_the_aux_head_and_leaves_the_encoders_as_they_were(views_dir, tmp_path):
    from policy.pretrain import pretrain
    from policy.testing import TINY, hash_embedder, synthetic_dataset

    data = synthetic_dataset(tmp_path / "data", episodes=4, smooth=True)
    over = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "lr": 3e-3, "warmup_steps": 1, "log_every": 5,
            "color_jitter": 0.0}
    first = pretrain(views_dir, data, dict(TINY), tmp_path / "pre", 5, over, threads=1, progress=False,
                     embedder=hash_embedder)
    head = pretrain(views_dir, data, dict(TINY), tmp_path / "head", 20, over, threads=1, progress=False,
                    embedder=hash_embedder, init_from=tmp_path / "pre", head_only=True)
    before, after = (torch.load(s["checkpoint"], weights_only=False) for s in (first, head))
    start = before["ema"]["model"]  # what the warm start took
    encoder = [k for k in start if k.startswith("obs_encoder.images.")]
    assert encoder
    for trained in (after["model"], after["ema"]["model"]):  # the EMA's averaging of equal weights may round
        for k in encoder:
            torch.testing.assert_close(trained[k], start[k], rtol=0, atol=1e-6)
        assert not torch.allclose(trained["aux_head.2.weight"], start["aux_head.2.weight"])
    assert json.loads((tmp_path / "head" / "dataset.json").read_text())["pretrain"]["head_only"] is True
    with pytest.raises(ValueError, match="give init_from"):
        pretrain(views_dir, data, dict(TINY), tmp_path / "bad", 1, over, threads=1, progress=False,
                 embedder=hash_embedder, head_only=True)


def test_carry_views_hold_the_named_object_on_its_way_to_the_bin():
    from datagen.views_carry import grasp_in_hand, place_carried
    from sim.kinematics import Kinematics
    from datagen.recorder import TCP_OFFSET_Z

    v = scene_views(300, 1, OFFSETS, image_size=SIZE, carry=3)
    assert len(v["proprio"]) == 4  # home, then three carrying views
    grasp = v["points"][0, 0]
    fingers = v["proprio"][:, 9]
    assert fingers[0] < 0.05 and np.all((fingers[1:] > 0.2) & (fingers[1:] < 0.9))  # closed on the object
    assert v["proprio"][1:, 2].min() > grasp[2] - 0.05
    np.testing.assert_array_equal(v["points"][1:], np.broadcast_to(v["points"][0], (3, 2, 3)))
    # the held object moves with the gripper as one body, still between both pads
    ep = build_episode("pick_place", 300, "heavy", "fast")
    kin = Kinematics.with_tcp_z(ep.world.variant, TCP_OFFSET_Z)
    target = ep.instance.params["target"]
    q_home = ep.world.arm_q()
    in_tcp = grasp_in_hand(ep.world, kin, target, grasp, 0.3, q_home)
    assert in_tcp is not None
    bin_above = StateView(ep.world).position(ep.instance.params["bin"]) + [0.0, 0.0, 0.15]
    T = ep.world.tcp_pose().copy()
    T[:3, 3] = bin_above
    place_carried(ep.world, kin, kin.ik(T, ep.world.arm_q()), target, in_tcp)
    state = StateView(ep.world)
    assert np.linalg.norm(ep.world.tcp_pose()[:3, 3] - bin_above) < 1e-3
    np.testing.assert_allclose(state.position(target), (ep.world.tcp_pose() @ in_tcp)[:3, 3], atol=1e-6)
    assert state.holding(target)


def test_carry_poses_follow_the_recorded_carry_from_above_the_grasp_to_above_the_bin():
    from datagen.views_carry import LIFT_ABOVE_RELEASE, carry_pose

    rng = np.random.default_rng(0)
    grasp, release = np.array([0.1, 0.35, 0.03]), np.array([-0.2, 0.6, 0.13])
    p = np.array([carry_pose(grasp, release, 0.4, rng)[:3, 3] for _ in range(600)])
    assert p[:, 2].min() >= grasp[2] and p[:, 2].max() < release[2] + LIFT_ABOVE_RELEASE + 0.06
    axis = (release - grasp)[:2] / np.linalg.norm((release - grasp)[:2])
    t = (p[:, :2] - grasp[:2]) @ axis / np.linalg.norm((release - grasp)[:2])
    off = np.abs((p[:, :2] - grasp[:2]) @ [-axis[1], axis[0]])
    assert np.median(off) < 0.05 and (t < 0.2).mean() > 0.25 and (t > 0.8).mean() > 0.25


def test_views_load_from_several_directories_and_name_an_empty_one(views_dir, tmp_path):
    generate(tmp_path / "more", range(302, 303), 2, OFFSETS, progress=False, image_size=SIZE, carry=1)
    both = load([views_dir, tmp_path / "more"])
    assert sorted(set(both["seed"].tolist())) == [300, 301, 302] and len(both["proprio"]) == 6 + 3
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty: no views"):
        load([views_dir, tmp_path / "empty"])


def test_validating_a_pretrain_run_leaves_out_what_its_untrained_denoiser_would_say(views_dir, tmp_path):
    from policy.pretrain import pretrain
    from policy.testing import TINY, hash_embedder, synthetic_dataset
    from policy.validate import validate_model

    data = synthetic_dataset(tmp_path / "data", episodes=6, smooth=True)
    over = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "warmup_steps": 1}
    pretrain(views_dir, data, dict(TINY), tmp_path / "pre", 2, over, threads=1, progress=False, embedder=hash_embedder)
    got = validate_model(tmp_path / "pre", data, samples=32, val_fraction=0.5, embedder=hash_embedder)
    assert "val_pregrasp_cm" in got and not any(k.endswith(("_loss", "chunk_cm")) for k in got)


def test_pretraining_fills_a_share_of_each_batch_with_recorded_frames(views_dir, tmp_path):
    from policy.config import load_policy_config
    from policy.data import PolicyDataset
    from policy.pretrain import EpisodeFrames, Views, mixed_batch, pretrain
    from policy.testing import TINY, hash_embedder, synthetic_dataset

    data = synthetic_dataset(tmp_path / "data", episodes=4, smooth=True)
    over = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "warmup_steps": 1, "log_every": 1}
    cfg = load_policy_config(TINY, over)
    ds = PolicyDataset(data, cfg, train=True, embedder=hash_embedder, uint8_images=True, max_cache_bytes=0)
    views = Views(views_dir, cfg, ds.normalizer, hash_embedder, None)
    b = mixed_batch(views, EpisodeFrames(ds), 0.25, np.random.default_rng(0), 8)
    assert all(x.shape[:2] == (8, cfg.obs_horizon) for x in b["images"].values())
    assert b["aux"].shape[0] == b["text"].shape[0] == b["proprio"].shape[0] == 8
    recorded = torch.stack([ds.aux_target(i) for i in range(len(ds))])
    found = [bool((recorded == row).all(1).any()) for row in b["aux"]]
    assert found == [False] * 6 + [True] * 2  # the views first, then round(0.25 * 8) recorded frames
    assert all(0.0 <= float(x.min()) and float(x.max()) <= 1.0 for x in b["images"].values())
    pretrain(views_dir, data, dict(TINY), tmp_path / "pre", 2, over, threads=1, progress=False,
             embedder=hash_embedder, episode_share=0.5, episode_tasks=("pick_place",))
    said = json.loads((tmp_path / "pre" / "dataset.json").read_text())["pretrain"]
    assert said["episode_share"] == 0.5 and said["episode_tasks"] == ["pick_place"]
    two = synthetic_dataset(tmp_path / "two", episodes=6, smooth=True, tasks=("pick_place", "stack"))
    both = PolicyDataset(two, cfg, train=True, embedder=hash_embedder, uint8_images=True, max_cache_bytes=0)
    stack = EpisodeFrames(both, ("stack",))
    assert 0 < len(stack.rows) < len(both) and {both.task_of(int(i)) for i in stack.rows} == {"stack"}
    with pytest.raises(ValueError, match="no training samples of drawer_open .* the data has pick_place, stack"):
        EpisodeFrames(both, ("drawer_open",))
    with pytest.raises(ValueError, match=r"episode_share 1.0: expected a share of the batch in \[0, 1\)"):
        pretrain(views_dir, data, dict(TINY), tmp_path / "bad", 1, over, threads=1, progress=False,
                 embedder=hash_embedder, episode_share=1.0)
    with pytest.raises(ValueError, match="episode_tasks \\['pick_place'\\] chooses the recorded frames of episode_share"):
        pretrain(views_dir, data, dict(TINY), tmp_path / "bad", 1, over, threads=1, progress=False,
                 embedder=hash_embedder, episode_tasks=("pick_place",))
