"""Flow matching (`objective = "flow"`): the straight noise-to-action path, its Euler sampler in torch and in
the exported bundle (parity), few-step sampling, and the loader's checks of an Euler schedule."""

import json
import shutil

import numpy as np
import pytest
import torch

from policy.bundle import Bundle, BundleError
from policy.config import load_policy_config
from policy.export import export
from policy.model import DiffusionPolicy
from policy.parity import CHUNK_TOL, STEP_TOL
from policy.schedule import flow_schedule, flow_step
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import train
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()


@pytest.mark.parametrize("steps", [1, 2, 3, 8])
@pytest.mark.parametrize("clip", [True, False])
def test_euler_steps_follow_a_straight_path_exactly(steps, clip):
    rng = np.random.default_rng(steps)
    a = rng.uniform(-0.9, 0.9, (16, 10))
    eps = rng.normal(size=(16, 10))
    sch = flow_schedule(100, steps)
    assert sch["timesteps"][0] == 99 and sch["sigma"][0] == 1.0 and sch["sigma_next"][-1] == 0.0
    x = eps
    for s, s_next in zip(sch["sigma"], sch["sigma_next"]):
        assert np.allclose(x, (1 - s) * a + s * eps)  # on the path at every step
        x = flow_step(x, eps - a, s, s_next, clip)  # the exact velocity
    np.testing.assert_allclose(x, a, atol=1e-12)


def test_clipping_keeps_the_action_estimate_in_range():
    x, u = np.full((2, 3), 0.5), np.full((2, 3), -2.0)  # a = x - s u = 2.5 at s = 1: out of [-1, 1]
    np.testing.assert_allclose(flow_step(x, u, 1.0, 0.0, clip=True), 1.0)
    np.testing.assert_allclose(flow_step(x, u, 1.0, 0.0, clip=False), 2.5)


def test_flow_loss_regresses_the_velocity_of_the_interpolant():
    cfg = load_policy_config("small", dict(TINY, objective="flow"))
    model = DiffusionPolicy(cfg)
    seen = {}

    def spy(x, t, cond):
        seen["x"] = x
        return x

    model.forward = spy
    g = torch.Generator().manual_seed(0)
    action = torch.rand(3, cfg.pred_horizon, cfg.action_dim, generator=g) * 2 - 1
    noise = torch.randn(action.shape, generator=g)
    t = torch.tensor([99, 49, 0])
    pred, target = model.denoise_target(torch.zeros(3, 4), action, noise, t)
    s = torch.tensor([1.0, 0.5, 0.01]).view(-1, 1, 1)
    torch.testing.assert_close(seen["x"], (1 - s) * action + s * noise)
    torch.testing.assert_close(target, noise - action)


@pytest.fixture(scope="module")
def flow_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("flow")
    data = synthetic_dataset(root / "data", episodes=6, smooth=True)
    train(data, dict(TINY, objective="flow", inference_steps=2), root / "run", steps=12, embedder=hash_embedder,
          progress=False, threads=1)
    return root / "run"


def test_flow_policy_learns_exports_and_matches_torch(flow_run, tmp_path):
    log = [json.loads(x) for x in (flow_run / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in log if "loss" in r]
    assert losses[-1] < losses[0]  # the velocity is learnable on the smooth synthetic reach
    m = export(flow_run, tmp_path / "b", cache_dir=CACHE)
    assert "ddim" not in m and len(m["euler"]["timesteps"]) == 2
    assert m["diffusion"]["prediction_type"] == "velocity" and m["diffusion"]["sampler"] == "euler"
    assert m["parity"]["step_max_abs_err"] <= STEP_TOL and m["parity"]["chunk_max_abs_err"] <= CHUNK_TOL
    b = Bundle.load(tmp_path / "b")
    assert b.sampler_steps == 2
    rng = np.random.default_rng(0)
    imgs = {c: rng.integers(0, 256, (b.obs_horizon, *b.image_size, 3), dtype=np.uint8) for c in b.cameras}
    proprio = np.zeros((b.obs_horizon, b.proprio_dim), np.float32)
    chunk = b.act(imgs, proprio, hash_embedder(["do pick_place"])[0], rng=rng)
    assert chunk.shape == (b.pred_horizon, b.action_dim) and np.isfinite(chunk).all()
    one = export(flow_run, tmp_path / "one", cache_dir=CACHE, inference_steps=1)  # a one-step sampler
    assert one["euler"] == {"timesteps": [99], "sigma": [1.0], "sigma_next": [0.0]}
    assert one["parity"]["chunk_max_abs_err"] <= CHUNK_TOL


@pytest.mark.parametrize("edit, reason", [
    (lambda m: m["euler"].__setitem__("sigma_next", [0.5, 0.1]), "euler schedule"),
    (lambda m: m["euler"].__setitem__("sigma", [1.5, 0.5]), "euler schedule"),
    (lambda m: m.__setitem__("ddim", {"timesteps": [9], "alpha_bar": [0.5], "alpha_bar_prev": [1.0]}),
     "exactly one sampler schedule"),
])
def test_load_refuses_a_broken_euler_schedule(flow_run, tmp_path, edit, reason):
    src = tmp_path / "b"
    export(flow_run, src, cache_dir=CACHE)
    Bundle.load(src, warmup=False)
    broken = tmp_path / "broken"
    shutil.copytree(src, broken)
    m = json.loads((broken / "manifest.json").read_text())
    edit(m)
    (broken / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match=reason):
        Bundle.load(broken, warmup=False)
