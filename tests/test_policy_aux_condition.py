"""aux_condition (the aux head's points fed to the denoiser) and warm-starting a run from another."""

import json

import numpy as np
import pytest
import torch

from policy.config import AUX_DIM, load_policy_config
from policy.model import DiffusionPolicy
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import train
from runtime.bench_runtime import test_cache_dir as cache_dir
from sim.config import ConfigError

AUX = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp"}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return synthetic_dataset(tmp_path_factory.mktemp("auxc") / "data", episodes=4, smooth=True)


@pytest.fixture(scope="module")
def source_run(data_dir, tmp_path_factory):
    run = tmp_path_factory.mktemp("auxc") / "source"
    train(data_dir, dict(TINY), run, steps=4, embedder=hash_embedder, progress=False, threads=1, overrides=AUX)
    return run


def _batch(cfg, B=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    h, w = cfg.crop_size
    return {"images": {c: torch.rand(B, cfg.obs_horizon, 3, h, w, generator=g) for c in cfg.cameras},
            "proprio": torch.randn(B, cfg.obs_horizon, cfg.proprio_dim, generator=g),
            "text": torch.randn(B, 384, generator=g), "action": torch.randn(B, cfg.pred_horizon, cfg.action_dim,
                                                                             generator=g),
            "aux": torch.randn(B, AUX_DIM, generator=g)}


def _loss_inputs(cfg):
    """A seeded model in eval mode, a batch, the action noise, timesteps and the aux noise for its loss."""
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    b = _batch(cfg)
    return model, b, torch.randn(3, cfg.pred_horizon, cfg.action_dim), torch.tensor([3, 50, 90]), torch.randn(3, AUX_DIM)


def test_aux_condition_needs_the_aux_head():
    with pytest.raises(ConfigError, match="aux_condition needs aux_target_weight"):
        load_policy_config(TINY, {"aux_condition": True})
    with pytest.raises(ConfigError, match="aux_condition_noise"):
        load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_noise": -1.0})


def test_inference_cond_ends_with_the_heads_prediction():
    plain = load_policy_config(TINY, AUX)
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True})
    assert cfg.global_cond_dim == plain.global_cond_dim + AUX_DIM
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    b = _batch(cfg)
    with torch.no_grad():
        cond = model.encode(b["images"], b["proprio"], b["text"])
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        assert cond.shape == (3, cfg.global_cond_dim)
        torch.testing.assert_close(cond[:, :-AUX_DIM], features)
        torch.testing.assert_close(cond[:, -AUX_DIM:], model.aux_points(features))


def test_training_feeds_the_true_points_plus_scaled_noise():
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_noise": 0.5})
    model, b, noise, t, z = _loss_inputs(cfg)
    mse = torch.nn.functional.mse_loss
    with torch.no_grad():
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        head = model.aux_points(features)
        fed = torch.cat([features, b["aux"] + 0.5 * z], dim=1)
        want = mse(*model.denoise_target(fed, b["action"], noise, t)) + mse(head, b["aux"])
        torch.testing.assert_close(model.loss(b, noise, t, z), want)
        moved = dict(b, aux=b["aux"] + 1.0)
        denoiser_term = [float(model.loss(x, noise, t, z) - mse(head, x["aux"])) for x in (b, moved)]
        assert abs(denoiser_term[0] - denoiser_term[1]) > 1e-6  # the denoiser sees the fed points


def test_the_release_point_can_have_its_own_teacher_forcing_noise():
    with pytest.raises(ConfigError, match="aux_release_noise"):
        load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_release_noise": -0.1})
    with pytest.raises(ConfigError, match="aux_release_noise 0.02 needs aux_condition"):
        load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_source": "head",
                                  "aux_release_noise": 0.02})
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_noise": 0.5,
                                    "aux_release_noise": 0.0})
    model, b, noise, t, z = _loss_inputs(cfg)
    mse = torch.nn.functional.mse_loss
    with torch.no_grad():
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        fed = b["aux"].clone()
        fed[:, :3] += 0.5 * z[:, :3]  # the grasp point noisy, the release point as recorded
        want = mse(*model.denoise_target(torch.cat([features, fed], dim=1), b["action"], noise, t))
        torch.testing.assert_close(model.loss(b, noise, t, z), want + mse(model.aux_points(features), b["aux"]))
    default = DiffusionPolicy(load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_noise": 0.5}))
    torch.testing.assert_close(z.new_tensor(default.cfg.aux_noise_std), torch.full((AUX_DIM,), 0.5))


def test_head_source_trains_the_denoiser_on_what_inference_feeds():
    with pytest.raises(ConfigError, match="aux_condition_source 'head' needs aux_condition"):
        load_policy_config(TINY, {**AUX, "aux_condition_source": "head"})
    with pytest.raises(ConfigError, match="aux_condition_source"):
        load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_source": "oracle"})
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True, "aux_condition_source": "head"})
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    b = _batch(cfg)
    noise, t = torch.randn(3, cfg.pred_horizon, cfg.action_dim), torch.tensor([3, 50, 90])
    mse = torch.nn.functional.mse_loss
    with torch.no_grad():
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        head = model.aux_points(features)
        cond = model.cond_from(features, b["proprio"])
        want = mse(*model.denoise_target(cond, b["action"], noise, t)) + mse(head, b["aux"])
        torch.testing.assert_close(model.loss(b, noise, t, torch.randn(3, AUX_DIM)), want)
    # the head learns from its own loss only: the denoiser's loss sends it nothing through the fed points
    grads = []
    for full in (True, False):
        model.zero_grad()
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        (model.loss(b, noise, t) if full else mse(model.aux_points(features), b["aux"])).backward()
        grads.append([p.grad.clone() for p in model.aux_head.parameters()])
    for with_denoiser, alone in zip(*grads):
        torch.testing.assert_close(with_denoiser, alone)


def test_warm_start_reproduces_the_source_then_records_it(data_dir, source_run, tmp_path):
    from policy import warm_start
    from policy.train import load_run_model

    source, _, _ = load_run_model(source_run)
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True})
    model = DiffusionPolicy(cfg).eval()
    record = warm_start.load_into(model, source_run)
    assert record["step"] == 4 and record["grown"] == [
        f"unet.film_cond.1.weight ({model.unet.film_dim}, {cfg.global_cond_dim - AUX_DIM}) -> "
        f"({model.unet.film_dim}, {cfg.global_cond_dim})"]
    b = _batch(cfg)
    x, t = torch.randn(3, cfg.pred_horizon, cfg.action_dim), torch.tensor([1, 40, 99])
    with torch.no_grad():
        old = source(x, t, source.encode(b["images"], b["proprio"], b["text"]))
        new = model(x, t, model.encode(b["images"], b["proprio"], b["text"]))
    torch.testing.assert_close(new, old)  # zero columns: the added inputs change nothing yet

    other = DiffusionPolicy(load_policy_config(TINY, {**AUX, "down_dims": [8, 16]}))
    with pytest.raises(ValueError, match="only a Linear's inputs may grow"):
        warm_start.load_into(other, source_run)

    run = tmp_path / "warm"
    train(data_dir, dict(TINY), run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides={**AUX, "aux_condition": True}, init_from=source_run)
    assert json.loads((run / "warm_start.json").read_text())["checkpoint"] == record["checkpoint"]
    assert (run / "stats.npz").read_bytes() == (source_run / "stats.npz").read_bytes()


@pytest.mark.parametrize("release_frame", ["tcp", "base"])
def test_an_aux_conditioned_bundle_exports_with_parity(data_dir, source_run, tmp_path, release_frame):
    from policy.bundle import Bundle
    from policy.export import export

    run = tmp_path / "run"
    train(data_dir, dict(TINY), run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides={**AUX, "aux_condition": True, "aux_release_frame": release_frame}, init_from=source_run)
    cache = cache_dir()
    m = export(run, tmp_path / "bundle", cache_dir=cache)
    # as export's own check: every step within 1e-4; the absolute chunk, which unnormalizes the steps' small
    # differences by the synthetic data's narrow action ranges, within 1e-3 (0.1 mm measured with a base-frame release)
    assert m["parity"]["step_max_abs_err"] <= 1e-4 and m["parity"]["cond_max_abs_err"] <= 1e-4
    assert m["parity"]["chunk_max_abs_err"] <= 1e-3
    assert m["dims"]["global_cond"] == load_policy_config(TINY, AUX).global_cond_dim + AUX_DIM
    assert m["training"]["warm_start"]["source"] == str(source_run)
    b = Bundle.load(tmp_path / "bundle")
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 255, (2, 32, 32, 3), dtype=np.uint8) for c in b.cameras}
    chunk = b.act(images, np.zeros((2, 16), np.float32) + [0.4, 0.1, 0.3, 1, 0, 0, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0],
                  b.embed("do pick_place"))
    assert chunk.shape == (b.pred_horizon, b.action_dim) and np.isfinite(chunk).all()


def test_a_base_frame_release_point_reaches_the_denoiser_relative_to_the_gripper(data_dir, tmp_path):
    from policy.action_frame import points_to_tcp, rot6d_of
    from policy.data import AUX_TCP_SCALE, aux_point_target
    from policy.train import load_run_model
    from policy.warm_start import source_normalizer

    with pytest.raises(ConfigError, match="aux_release_frame 'base' needs"):
        load_policy_config(TINY, {"aux_release_frame": "base"})
    rng = np.random.default_rng(3)
    poses = []
    for _ in range(4):  # gripper poses pointing down, turned and tilted a little
        yaw, tilt = rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3)
        Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        Rx = np.array([[1, 0, 0], [0, np.cos(np.pi + tilt), -np.sin(np.pi + tilt)],
                       [0, np.sin(np.pi + tilt), np.cos(np.pi + tilt)]])
        poses.append(np.concatenate([rng.uniform([-0.3, 0.3, 0.1], [0.3, 0.7, 0.4]), rot6d_of(Rz @ Rx)]))
    points = rng.uniform([-0.3, 0.3, 0.0], [0.3, 0.7, 0.2], (4, 2, 3))
    # the label: the grasp point relative to the gripper as before, the release point where it is
    label = aux_point_target(points[0], poses[0], "base")
    np.testing.assert_allclose(label[:3], points_to_tcp(points[0, :1], poses[0])[0] / AUX_TCP_SCALE, atol=1e-6)
    np.testing.assert_allclose(label[3:], points[0, 1] / AUX_TCP_SCALE, atol=1e-6)
    # the model turns it relative to the gripper with the run's own proprio stats, which its checkpoint keeps
    run = tmp_path / "run"
    train(data_dir, dict(TINY), run, steps=1, embedder=hash_embedder, progress=False, threads=1,
          overrides={**AUX, "aux_condition": True, "aux_release_frame": "base"})
    model, _, _ = load_run_model(run)
    norm = source_normalizer(run)
    proprio = np.zeros((4, model.cfg.proprio_dim), np.float32)
    proprio[:, :9] = np.stack(poses)
    fed = torch.stack([aux_point_target(p, q, "base") for p, q in zip(points, proprio)])
    got = model.points_for_denoiser(fed, torch.from_numpy(norm.normalize_proprio(proprio))[:, None])
    want = torch.stack([aux_point_target(p, q, "tcp") for p, q in zip(points, proprio)])
    torch.testing.assert_close(got, want, atol=1e-5, rtol=0)


def test_frozen_pretrained_parts_keep_the_warm_start_and_the_rest_trains(data_dir, source_run, tmp_path):
    from policy.train import load_run_model

    over = {**AUX, "aux_condition": True, "freeze_pretrained": True}
    with pytest.raises(ValueError, match="freeze_pretrained keeps the image encoders"):
        train(data_dir, dict(TINY), tmp_path / "cold", steps=1, embedder=hash_embedder, progress=False, threads=1,
              overrides=over)
    train(data_dir, dict(TINY), tmp_path / "run", steps=3, embedder=hash_embedder, progress=False, threads=1,
          overrides=over, init_from=source_run)
    before, _, _ = load_run_model(source_run)
    after = torch.load(sorted((tmp_path / "run" / "checkpoints").glob("*.pt"))[-1], weights_only=False)["model"]
    for name, p in before.state_dict().items():
        if name.startswith(("obs_encoder.images.", "aux_head.")):
            torch.testing.assert_close(after[name], p)
    assert not torch.equal(after["unet.film_cond.1.weight"][:, :-AUX_DIM],
                           before.state_dict()["unet.film_cond.1.weight"])


def test_image_cond_dropout_hides_the_image_features_from_the_denoiser_only(data_dir, tmp_path):
    with pytest.raises(ConfigError, match="image_cond_dropout 1.0 needs aux_condition"):
        load_policy_config(TINY, {**AUX, "image_cond_dropout": 1.0})
    cfg = load_policy_config(TINY, {**AUX, "aux_condition": True, "obs_horizon": 2, "image_cond_dropout": 1.0})
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    b, other = _batch(cfg), _batch(cfg, seed=1)
    width = len(cfg.cameras) * cfg.image_feature_dim
    per_step = width + cfg.proprio_feature_dim
    with torch.no_grad():
        cond = model.encode(b["images"], b["proprio"], b["text"])
        features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        for s in range(cfg.obs_horizon):  # images hidden, proprio shown, at every observation step
            assert not cond[:, s * per_step:s * per_step + width].any()
            torch.testing.assert_close(cond[:, s * per_step + width:(s + 1) * per_step],
                                       features[:, s * per_step + width:(s + 1) * per_step])
        torch.testing.assert_close(cond[:, -AUX_DIM:], model.aux_points(features))
        # Other images reach the denoiser only through the head's points: same points, same cond.
        swapped = model.obs_encoder(other["images"], b["proprio"], b["text"])
        fed = torch.cat([model.hide_images(swapped, torch.zeros(1, 1)), cond[:, -AUX_DIM:]], dim=1)
        torch.testing.assert_close(fed, cond)

        noise, t = torch.randn(3, cfg.pred_horizon, cfg.action_dim), torch.tensor([3, 50, 90])
        head_term = torch.nn.functional.mse_loss(model.aux_points(features), b["aux"])
        shown = dict(b, images=other["images"])  # the aux head's term differs; the denoiser's must not
        other_head = model.aux_points(model.obs_encoder(other["images"], b["proprio"], b["text"]))
        hidden = [float(model.loss(x, noise, t, image_keep=torch.zeros(3)) - h) for x, h in
                  ((b, head_term), (shown, torch.nn.functional.mse_loss(other_head, b["aux"])))]
        assert abs(hidden[0] - hidden[1]) < 1e-6
        kept = [float(model.loss(x, noise, t, image_keep=torch.ones(3)) - h) for x, h in
                ((b, head_term), (shown, torch.nn.functional.mse_loss(other_head, b["aux"])))]
        assert abs(kept[0] - kept[1]) > 1e-6  # kept samples do show the images

    half = load_policy_config(TINY, {**AUX, "aux_condition": True, "image_cond_dropout": 0.5})
    torch.manual_seed(0)
    shown_model = DiffusionPolicy(half).eval()
    with torch.no_grad():  # below 1, inference shows the images
        torch.testing.assert_close(shown_model.encode(b["images"], b["proprio"], b["text"])[:, :-AUX_DIM],
                                   shown_model.obs_encoder(b["images"], b["proprio"], b["text"]))
    run = tmp_path / "run"
    summary = train(data_dir, dict(TINY), run, steps=2, embedder=hash_embedder, progress=False, threads=1,
                    overrides={**AUX, "aux_condition": True, "image_cond_dropout": 0.5})
    assert np.isfinite(summary["final_loss"])
