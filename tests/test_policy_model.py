"""Policy networks, config, schedule and normalization: shapes, sizes, exact rewrites, round trips."""

import numpy as np
import pytest
import torch

from policy.config import PRESETS, PolicyConfig, config_from_dict, load_policy_config, preset
from policy.model import (ConditionalUnet1D, DiffusionPolicy, ImageEncoder, ObsEncoder, SpatialSoftmax, count_params,
                          film_dim, prepare_images)
from policy.normalize import Normalizer
from policy.action_frame import orthonormalize_rot6d
from policy.sampling import sample
from policy.schedule import alphas_cumprod, ddim_schedule, ddim_step
from policy.testing import TINY
from sim.config import ConfigError


def test_presets_sizes_and_round_trip():
    small, full = DiffusionPolicy(preset("small")), DiffusionPolicy(preset("full"))
    assert 2e6 <= count_params(small) <= 6e6  # trains on 2 CPU cores in minutes
    assert count_params(full) > 10 * count_params(small)
    for name in PRESETS:
        cfg = preset(name)
        assert (cfg.obs_horizon, cfg.pred_horizon, cfg.action_horizon) == (2, 16, 8)
        assert cfg.num_train_timesteps == 100 and cfg.inference_steps <= 8
        assert config_from_dict(cfg.to_dict()) == cfg
    assert load_policy_config("full", {"inference_steps": 4}).inference_steps == 4


@pytest.mark.parametrize("bad", [{"action_horizon": 16}, {"pred_horizon": 18}, {"crop_size": [200, 200]},
                                 {"down_dims": [60, 128, 256]}, {"beta_schedule": "cosine"}, {"lr": -1.0}])
def test_config_rejects_inconsistent_values(bad):
    with pytest.raises(ConfigError):
        load_policy_config("small", bad)


def test_config_toml(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text('preset = "full"\ninference_steps = 6\n')
    cfg = load_policy_config(path)
    assert cfg.preset == "full" and cfg.down_dims == (256, 512, 1024) and cfg.inference_steps == 6
    path.write_text("infrence_steps = 6\n")
    with pytest.raises(ConfigError, match="inference_steps"):
        load_policy_config(path)


def test_module_shapes():
    cfg = load_policy_config(TINY)
    B, To, Tp, Da = 3, cfg.obs_horizon, cfg.pred_horizon, cfg.action_dim
    h, w = cfg.crop_size
    enc = ImageEncoder((8, 16), (1, 1), 5, 12)
    assert enc(torch.rand(7, 3, h, w)).shape == (7, 12)
    assert SpatialSoftmax(4, 6)(torch.randn(2, 4, 5, 5)).shape == (2, 12)
    obs = ObsEncoder(cfg)
    images = {c: torch.rand(B, To, 3, h, w) for c in cfg.cameras}
    cond = obs(images, torch.randn(B, To, cfg.proprio_dim), torch.randn(B, 384))
    assert cond.shape == (B, cfg.global_cond_dim)
    unet = ConditionalUnet1D(Da, cfg.global_cond_dim, cfg.step_embed_dim, cfg.down_dims, cfg.kernel_size,
                             cfg.group_norm_groups)
    x, t = torch.randn(B, Tp, Da), torch.randint(0, 100, (B,))
    out = unet(x, t, cond)
    assert out.shape == (B, Tp, Da)
    assert unet.condition(cond).shape == (B, film_dim(cfg)) == (B, unet.film_dim)
    torch.testing.assert_close(unet.denoise(x, t, unet.condition(cond)), out)  # the per-chunk split is exact
    frames = torch.randint(0, 256, (B, To, *cfg.image_size, 3), dtype=torch.uint8)
    assert prepare_images(frames, cfg.crop_size).shape == (B, To, 3, h, w)


def test_encoder_strides_set_the_keypoint_map_and_are_validated():
    x = torch.rand(2, 3, 32, 32)
    default = ImageEncoder((8, 16, 32), (1, 1, 1), 4, 12)
    finer = ImageEncoder((8, 16, 32), (1, 1, 1), 4, 12, strides=(1, 2, 1))
    assert default.stages(default.stem(x)).shape[-2:] == (2, 2)
    assert finer.stages(finer.stem(x)).shape[-2:] == (4, 4) and finer(x).shape == (2, 12)
    with pytest.raises(ConfigError, match="encoder_strides"):
        load_policy_config({**TINY, "encoder_strides": [1, 2, 2]})


def test_spatial_softmax_sharpness_is_learned():
    ss = SpatialSoftmax(4, 3)
    x = torch.randn(2, 4, 6, 6)
    soft = ss(x)
    with torch.no_grad():
        ss.log_beta.fill_(3.0)
    sharp = ss(x)
    assert sharp.abs().mean() > soft.abs().mean()  # peaked attention: keypoints leave the centre
    assert any(p is ss.log_beta for p in ss.parameters())


def test_instruction_film_starts_as_identity_and_then_steers_the_keypoints():
    torch.manual_seed(0)
    plain, filmed = ImageEncoder((8, 16), (1, 1), 5, 12), ImageEncoder((8, 16), (1, 1), 5, 12, film_dim=384)
    filmed.load_state_dict(plain.state_dict(), strict=False)
    x, a, b = torch.rand(2, 3, 32, 32), torch.randn(2, 384), torch.randn(2, 384)
    torch.testing.assert_close(filmed(x, a), plain(x))  # zero-initialised: an untrained FiLM changes nothing
    torch.nn.init.normal_(filmed.film.weight, std=0.05)
    assert not torch.allclose(filmed(x, a), filmed(x, b), atol=1e-4)  # two instructions, two readings of one image
    torch.testing.assert_close(filmed(x, a), filmed(x, a))


def test_film_split_equals_paper_formulation():
    """Linear(Mish([e, c])) == W_e Mish(e) + b + W_c Mish(c): the stacked/split FiLM is Diffusion Policy's."""
    cfg = load_policy_config(TINY)
    unet = DiffusionPolicy(cfg).unet
    e, c = torch.randn(2, cfg.step_embed_dim), torch.randn(2, cfg.global_cond_dim)
    W = torch.cat([unet.film_step[1].weight, unet.film_cond[1].weight], dim=1)
    ref = torch.nn.functional.mish(torch.cat([e, c], dim=1)) @ W.T + unet.film_step[1].bias
    torch.testing.assert_close(unet.film_step(e) + unet.condition(c), ref)


def test_loss_and_sampler_shapes():
    cfg = load_policy_config(TINY)
    model = DiffusionPolicy(cfg)
    B = 2
    batch = {"images": {c: torch.rand(B, cfg.obs_horizon, 3, *cfg.crop_size) for c in cfg.cameras},
             "proprio": torch.randn(B, cfg.obs_horizon, 16), "text": torch.randn(B, 384),
             "action": torch.rand(B, cfg.pred_horizon, 10) * 2 - 1}
    loss = model.loss(batch, torch.randn(B, cfg.pred_horizon, 10), torch.randint(0, 100, (B,)))
    assert loss.ndim == 0 and torch.isfinite(loss)
    cond = model.encode(batch["images"], batch["proprio"], batch["text"])
    x = sample(model, cond, torch.randn(B, cfg.pred_horizon, 10))
    assert x.shape == (B, cfg.pred_horizon, 10) and float(x.abs().max()) <= 1.0 + 1e-5


def test_schedule():
    ab = alphas_cumprod(100)
    assert ab.shape == (100,) and np.all(np.diff(ab) < 0) and 0.99 < ab[0] < 1 and ab[-1] < 1e-5
    s = ddim_schedule(100, 8)
    assert s["timesteps"][0] == 99 and len(s["timesteps"]) == 8 and s["alpha_bar_prev"][-1] == 1.0
    assert s["alpha_bar_prev"][:-1] == s["alpha_bar"][1:]
    # exact noise prediction recovers x0 in one step to alpha_bar = 1
    x0, eps = np.random.default_rng(0).uniform(-1, 1, (16, 10)), np.random.default_rng(1).normal(size=(16, 10))
    a = s["alpha_bar"][3]
    xt = np.sqrt(a) * x0 + np.sqrt(1 - a) * eps
    np.testing.assert_allclose(ddim_step(xt, eps, a, 1.0), x0, atol=1e-9)


def test_normalization_round_trip():
    rng = np.random.default_rng(0)
    proprio = rng.normal(size=(500, 16)) * [1, 2, 3, 1, 1, 1, 1, 1, 1, 0.5, 2, 2, 2, 2, 2, 2] + 5
    proprio[:, 9] = 0.25  # constant gripper
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    proprio[:, 3:9] = np.concatenate([R[:, 0], R[:, 1]])
    action = rng.uniform(-0.4, 0.9, size=(500, 10))
    n = Normalizer.fit(proprio, action)
    p, a = n.normalize_proprio(proprio), n.normalize_action(action)
    np.testing.assert_allclose(n.unnormalize_proprio(p), proprio, atol=1e-5)
    np.testing.assert_allclose(n.unnormalize_action(a), action, atol=1e-5)
    moving = [0, 1, 2, 10, 11, 12, 13, 14, 15]
    assert np.allclose(p[:, moving].min(0), -1, atol=1e-5) and np.allclose(p[:, moving].max(0), 1, atol=1e-5)
    np.testing.assert_array_equal(p[:, 3:9], proprio[:, 3:9].astype(np.float32))  # rot6d left as is
    assert np.allclose(p[:, 9], 0.0)  # a constant maps to 0 and back exactly
    assert np.allclose(a[:, [0, 1, 2, 9]].min(0), -1, atol=1e-5)


def test_normalizer_save_load(tmp_path):
    n = Normalizer.fit(np.random.rand(50, 16), np.random.rand(50, 10))
    n.save(tmp_path / "s.npz")
    m = Normalizer.load(tmp_path / "s.npz")
    for k, v in n.to_dict().items():
        np.testing.assert_array_equal(v, getattr(m, k))


def test_orthonormalize_rot6d():
    a = np.random.default_rng(0).normal(size=(5, 10)).astype(np.float32)
    out = orthonormalize_rot6d(a)
    x, y = out[:, 3:6], out[:, 6:9]
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(y, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose((x * y).sum(1), 0, atol=1e-5)
    np.testing.assert_array_equal(out[:, [0, 1, 2, 9]], a[:, [0, 1, 2, 9]])


def test_default_config_is_valid():
    PolicyConfig().validate()


def test_aux_target_loss_trains_the_image_features_only_when_asked():
    from policy.data import grasp_and_release, grasp_and_release_steps

    grip = np.array([0, 0, 1, 1, 1, 0, 0], np.float32)  # recorded command: closes at step 2, opens at step 5
    act = np.zeros((7, 10), np.float32)
    act[:, 0], act[:, -1] = np.arange(7), grip
    assert grasp_and_release_steps(act) == (2, 5)
    assert grasp_and_release(act, (2, 5)).tolist() == [2, 0, 0, 5, 0, 0]
    act[:, -1] = 0  # never closes: both are the last step
    assert grasp_and_release_steps(act) == (6, 6)

    cfg = load_policy_config({**TINY, "aux_target_weight": 1.0})
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg)
    assert DiffusionPolicy(load_policy_config(TINY)).aux_head is None
    B, To, (h, w) = 2, cfg.obs_horizon, cfg.crop_size
    batch = {"images": {c: torch.rand(B, To, 3, h, w) for c in cfg.cameras},
             "proprio": torch.randn(B, To, cfg.proprio_dim), "text": torch.randn(B, 384), "action": torch.randn(B, cfg.pred_horizon, cfg.action_dim),
             "aux": torch.randn(B, 6)}
    noise, t = torch.randn(B, cfg.pred_horizon, cfg.action_dim), torch.randint(0, 100, (B,))
    with_aux = model.loss(batch, noise, t)
    model.cfg = load_policy_config(TINY)
    plain = model.loss(batch, noise, t)
    model.cfg = cfg
    assert with_aux > plain
    cond = model.encode(batch["images"], batch["proprio"], batch["text"])
    feats = torch.cat([model.obs_encoder.images[c](batch["images"][c][:, -1], batch["text"]) for c in cfg.cameras], 1)
    torch.testing.assert_close(model.image_features(cond), feats)  # the slice is the newest step's cameras


def test_tcp_frame_aux_target_is_the_offset_the_gripper_sees():
    from datagen.schema import rot6d
    from policy.data import AUX_TCP_SCALE, relative_to_tcp

    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # TCP yawed 90 degrees: its x axis is the base's y
    proprio = np.concatenate([[0.1, 0.2, 0.3], rot6d(Rz), np.zeros(7)])
    points = np.array([[0.1, 0.2 + AUX_TCP_SCALE, 0.3], [0.1 - 0.5, 0.2, 0.3 - 0.25]])
    np.testing.assert_allclose(relative_to_tcp(points, proprio).numpy(), [1, 0, 0, 0, 2, -1], atol=1e-6)
    cfg = load_policy_config({**TINY, "aux_target_weight": 1.0, "aux_target_frame": "tcp"})
    assert cfg.aux_target_frame == "tcp"
    with pytest.raises(ConfigError, match="aux_target_frame"):
        load_policy_config({**TINY, "aux_target_frame": "world"})
