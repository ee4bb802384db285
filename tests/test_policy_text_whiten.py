"""Whitening of the instruction embedding (policy.text_whiten, config text_whiten)."""

import os
import tempfile
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from policy.config import load_policy_config
from policy.model import DiffusionPolicy
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.text_whiten import TextWhitening, fit_whitening, prepare
from policy.train import train

AUX = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp"}


def _instructions(rng, n=60, dim=384):
    """Unit-ish embeddings that vary a lot along one direction (the phrasing) and little along another (the bin)."""
    base, big, small = (v / np.linalg.norm(v) for v in rng.normal(size=(3, dim)))
    small -= (small @ big) * big
    small /= np.linalg.norm(small)
    phrasing, bin_ = rng.choice([-1.0, 1.0], n), rng.choice([-1.0, 1.0], n)
    return base + 0.5 * phrasing[:, None] * big + 0.05 * bin_[:, None] * small, big, small


def test_whitening_brings_a_small_variation_up_to_the_size_of_a_large_one():
    x, big, small = _instructions(np.random.default_rng(0))
    mean, w = fit_whitening(x, ridge=1e-4)
    assert np.allclose(w, w.T, atol=1e-6)
    raw = [np.linalg.norm(d) for d in (big, 0.1 * small)]
    white = [np.linalg.norm(d @ w) for d in (big, 0.1 * small)]
    assert raw[1] / raw[0] == pytest.approx(0.1, rel=1e-3)
    assert 0.8 < white[1] / white[0] < 1.25  # the bin reads as loud as the phrasing
    cov = np.cov(((x - mean) @ w).T, bias=True)
    assert np.linalg.eigvalsh(cov).max() == pytest.approx(1.0, abs=0.02)
    # the ridge keeps a direction the instructions never vary along from being blown up
    unseen = np.linalg.svd(x - mean)[2][-1]
    assert np.linalg.norm(unseen @ w) == pytest.approx(1 / np.sqrt(1e-4), rel=1e-3)


def test_whitening_refuses_a_single_instruction_and_a_ridge_of_zero():
    x, _, _ = _instructions(np.random.default_rng(1))
    with pytest.raises(ValueError, match="at least 2 distinct instructions"):
        fit_whitening(x[:1], 1e-3)
    with pytest.raises(ValueError, match="ridge must be > 0"):
        fit_whitening(x, 0.0)


def test_the_module_is_the_identity_until_fitted_then_stores_float16_exact_values():
    x, _, _ = _instructions(np.random.default_rng(2))
    m = TextWhitening(384)
    t = torch.randn(3, 384)
    torch.testing.assert_close(m(t), t)
    assert not m.is_fitted
    m.fit_(x, 1e-3)
    assert m.is_fitted and torch.equal(m.matrix.half().float(), m.matrix) and torch.equal(m.mean.half().float(), m.mean)
    mean, w = fit_whitening(x, 1e-3)
    torch.testing.assert_close(m(t), (t - torch.from_numpy(mean)) @ torch.from_numpy(w), rtol=2e-3, atol=2e-3)


def test_the_obs_encoder_reads_the_whitened_instruction():
    cfg = load_policy_config(TINY, {"text_whiten": 1e-3})
    off = DiffusionPolicy(load_policy_config(TINY))
    on = DiffusionPolicy(cfg)
    on.load_state_dict(off.state_dict(), strict=False)
    g = torch.Generator().manual_seed(0)
    h, w = cfg.crop_size
    images = {c: torch.rand(2, cfg.obs_horizon, 3, h, w, generator=g) for c in cfg.cameras}
    proprio, text = torch.randn(2, cfg.obs_horizon, cfg.proprio_dim, generator=g), torch.randn(2, 384, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(on.encode(images, proprio, text), off.encode(images, proprio, text))  # identity
        on.obs_encoder.text_whiten.fit_(_instructions(np.random.default_rng(3))[0], 1e-3)
        assert not torch.allclose(on.encode(images, proprio, text), off.encode(images, proprio, text))
        # the feature cache's path (camera_features) whitens too
        white = on.obs_encoder.text_whiten(text)
        torch.testing.assert_close(on.obs_encoder.camera_features(images, text),
                                   off.obs_encoder.camera_features(images, white))


def test_prepare_fits_a_new_model_on_the_distinct_instructions_and_a_warm_one_must_bring_its_own():
    x, _, _ = _instructions(np.random.default_rng(4), n=5)
    texts = [f"t{i}" for i in range(5)]
    ds = SimpleNamespace(instructions=texts * 3, text_row={t: i for i, t in enumerate(texts)},
                         text_table=torch.from_numpy(x.astype(np.float32)))
    model = DiffusionPolicy(load_policy_config(TINY, {"text_whiten": 1e-3}))
    assert prepare(model, ds, None) == {"ridge": 1e-3, "instructions": 5}
    assert model.obs_encoder.text_whiten.is_fitted
    assert prepare(model, ds, {"source": "runs/pre"}) == {"ridge": 1e-3, "from": "runs/pre"}
    with pytest.raises(ValueError, match="trained without it"):
        prepare(DiffusionPolicy(load_policy_config(TINY, {"text_whiten": 1e-3})), ds, {"source": "runs/old"})
    assert prepare(DiffusionPolicy(load_policy_config(TINY)), ds, None) is None


def test_a_whitened_run_warm_starts_another_and_exports_with_parity(tmp_path):
    from policy import warm_start
    from policy.bundle import Bundle
    from policy.export import export

    data = synthetic_dataset(tmp_path / "data", episodes=4, tasks=("pick_place", "stack"), smooth=True)
    over = {**AUX, "text_whiten": 1e-3, "include_failures": True}  # both tasks: two instructions
    train(data, dict(TINY), tmp_path / "src", steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides=over)
    src = torch.load(warm_start.source_checkpoint(tmp_path / "src"), weights_only=False)["ema"]["model"]
    assert src["obs_encoder.text_whiten.fitted"] == 1.0
    run = tmp_path / "run"
    train(data, dict(TINY), run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides={**over, "aux_condition": True, "freeze_pretrained": True}, init_from=tmp_path / "src")
    ckpt = torch.load(warm_start.source_checkpoint(run), weights_only=False)["ema"]["model"]
    torch.testing.assert_close(ckpt["obs_encoder.text_whiten.matrix"], src["obs_encoder.text_whiten.matrix"])
    train(data, dict(TINY), tmp_path / "plain", steps=1, embedder=hash_embedder, progress=False, threads=1,
          overrides={**AUX, "include_failures": True})
    with pytest.raises(ValueError, match="trained without it"):  # its encoders read the raw embedding
        train(data, dict(TINY), tmp_path / "bad", steps=1, embedder=hash_embedder, progress=False, threads=1,
              overrides=over, init_from=tmp_path / "plain")
    cache = os.path.join(tempfile.gettempdir(), f"sudd-test-cache-{os.getuid()}")
    m = export(run, tmp_path / "bundle", cache_dir=cache)
    assert m["parity"]["chunk_max_abs_err"] <= 1e-4 and m["parity"]["step_max_abs_err"] <= 1e-4
    b = Bundle.load(tmp_path / "bundle")
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 255, (2, 32, 32, 3), dtype=np.uint8) for c in b.cameras}
    proprio = np.zeros((2, 16), np.float32) + [0.4, 0.1, 0.3, 1, 0, 0, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0]
    assert np.isfinite(b.act(images, proprio, b.embed("do pick_place"))).all()
