"""sudd oracle-eval: the denoiser given the sim's true aux points, in closed loop as sudd eval runs it."""

import json

import numpy as np
import pytest
import torch

from datagen.schema import rot6d
from policy.config import AUX_DIM, load_policy_config
from policy.data import relative_to_tcp
from policy.model import DiffusionPolicy
from policy.oracle_eval import OracleAuxPolicy, TruePoints, oracle_eval
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import load_run_model, train
from policy.warm_start import source_normalizer
from runtime.evaluate import run_policy_episode
from sim.build import build_episode
from sim.state import StateView

AUXC = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "aux_condition": True}
OFFSETS = {"grasp": np.array([0.0, 0.0, 0.01]), "release": np.array([0.0, 0.0, 0.13])}
SEED = 100000


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("oracle")
    data = synthetic_dataset(root / "data", episodes=4, smooth=True)
    train(data, dict(TINY), root / "run", steps=4, embedder=hash_embedder, progress=False, threads=1,
          overrides=AUXC)
    return root / "run"


def _policy(run) -> OracleAuxPolicy:
    model, _, _ = load_run_model(run)
    return OracleAuxPolicy(model, source_normalizer(run), hash_embedder)


def _observation(cfg, ep) -> tuple[dict, np.ndarray]:
    """Random camera frames and the arm's proprio as the episode starts, as the policy is given them."""
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (cfg.obs_horizon, *cfg.image_size, 3), dtype=np.uint8) for c in cfg.cameras}
    T = ep.world.tcp_pose()
    proprio = np.tile(np.concatenate([T[:3, 3], rot6d(T[:3, :3]), [0.0], ep.world.arm_q()]),
                      (cfg.obs_horizon, 1)).astype(np.float32)
    return images, proprio


def test_true_points_are_the_object_and_bin_plus_the_offsets_and_bias_moves_the_grasp_sideways():
    ep = build_episode("pick_place", SEED, "heavy", "fast")
    state = StateView(ep.world)
    exact, biased = TruePoints(OFFSETS, 0.0, SEED), TruePoints(OFFSETS, 2.0, SEED)
    exact(ep.world, ep.instance)
    biased(ep.world, ep.instance)
    np.testing.assert_allclose(exact.points[0], state.position(ep.instance.params["target"]) + OFFSETS["grasp"])
    np.testing.assert_allclose(exact.points[1], state.position(ep.instance.params["bin"]) + OFFSETS["release"])
    shift = biased.points - exact.points
    assert np.linalg.norm(shift[0]) == pytest.approx(0.02) and shift[0, 2] == 0.0 and not shift[1].any()
    other = TruePoints(OFFSETS, 2.0, SEED + 1)
    other(ep.world, ep.instance)
    assert not np.allclose(other.points[0], biased.points[0])  # a direction per episode


def test_stacks_true_points_are_the_top_block_and_the_one_it_goes_on(run, tmp_path):
    ep = build_episode("stack", SEED, "heavy", "fast")
    state = StateView(ep.world)
    truth = TruePoints(OFFSETS, 0.0, SEED, "stack")
    truth(ep.world, ep.instance)
    np.testing.assert_allclose(truth.points[0], state.position(ep.instance.params["top"]) + OFFSETS["grasp"])
    np.testing.assert_allclose(truth.points[1], state.position(ep.instance.params["bottom"]) + OFFSETS["release"])
    with pytest.raises(ValueError, match="oracle-eval --task drawer_open: expected a family that carries"):
        oracle_eval(run, tmp_path / "ev", episodes=1, task="drawer_open", progress=False)


def test_the_denoiser_gets_the_true_points_in_the_tcp_frame_and_the_head_is_bypassed(run):
    policy = _policy(run)
    cfg = policy.model.cfg
    ep = build_episode("pick_place", SEED, "heavy", "fast")
    policy.truth = TruePoints(OFFSETS, 0.0, SEED)
    policy.truth(ep.world, ep.instance)
    images, proprio = _observation(cfg, ep)
    emb = policy.embed("move the blue block to the left bin")
    cond = policy.cond(images, proprio, emb)
    torch.testing.assert_close(cond[0, -AUX_DIM:], relative_to_tcp(policy.truth.points, proprio[-1]))
    with torch.no_grad():
        from policy.model import prepare_images

        imgs = {c: prepare_images(torch.from_numpy(images[c])[None], cfg.crop_size) for c in cfg.cameras}
        head = policy.model.encode(imgs, torch.from_numpy(policy.normalizer.normalize_proprio(proprio))[None],
                                   torch.from_numpy(emb)[None])
    torch.testing.assert_close(cond[0, :-AUX_DIM], head[0, :-AUX_DIM])
    assert not torch.allclose(cond[0, -AUX_DIM:], head[0, -AUX_DIM:])
    chunk = policy.act(images, proprio, emb, rng=np.random.default_rng(1))
    assert chunk.shape == (cfg.pred_horizon, cfg.action_dim) and np.isfinite(chunk).all()
    # one point true, the other the head's
    for which, k in (("grasp", 0), ("release", 1)):
        one = OracleAuxPolicy(policy.model, policy.normalizer, hash_embedder, true_points=which)
        one.truth = policy.truth
        c = one.cond(images, proprio, emb)[0, -AUX_DIM:]
        true, own = slice(3 * k, 3 * k + 3), slice(3 - 3 * k, 6 - 3 * k)
        torch.testing.assert_close(c[true], cond[0, -AUX_DIM:][true])
        torch.testing.assert_close(c[own], head[0, -AUX_DIM:][own])
    with pytest.raises(ValueError, match="true_points 'bin'"):
        OracleAuxPolicy(policy.model, policy.normalizer, hash_embedder, true_points="bin")


def test_oracle_eval_runs_episodes_through_the_controller_and_writes_them(run, tmp_path):
    policy = _policy(run)
    policy.truth = TruePoints(OFFSETS, 0.0, SEED)
    out = run_policy_episode(policy, "pick_place", SEED, dr="heavy", observer=policy.truth, time_limit_factor=0.05)
    assert out.chunks > 0 and policy.truth.points is not None
    rows = oracle_eval(run, tmp_path / "ev", episodes=1, seed_offset=SEED, bias_cm=1.0, progress=False,
                       time_limit_factor=0.05)
    recs = [json.loads(x) for x in (tmp_path / "ev" / "results.jsonl").read_text().splitlines()]
    assert [r["seed"] for r in recs] == [SEED] and recs[0]["suite"] == "oracle+1cm" and recs[0]["chunks"] > 0
    assert rows[0]["n"] == 1 and "oracle+1cm" in (tmp_path / "ev" / "results.md").read_text()
    # a fixed lag makes a rerun the same episode; the suite names the replaced point
    again = [oracle_eval(run, tmp_path / f"ev{i}", episodes=1, seed_offset=SEED, progress=False, time_limit_factor=0.05,
                         true_points="release", latency_ms=6.0) for i in (0, 1)]
    recs = [json.loads((tmp_path / f"ev{i}" / "results.jsonl").read_text()) for i in (0, 1)]
    assert again[0][0]["suite"] == recs[0]["suite"] == "oracle-release"
    assert recs[0]["inference_ms"]["n"] == recs[1]["inference_ms"]["n"] > 0
    assert recs[0]["closest_cm"] is not None and recs[1]["closest_cm"] == recs[0]["closest_cm"]


def test_a_run_without_aux_condition_is_refused_with_the_fields_named():
    model = DiffusionPolicy(load_policy_config(TINY, {"aux_target_weight": 1.0}))
    with pytest.raises(ValueError, match="aux_condition=False"):
        OracleAuxPolicy(model, None, hash_embedder)


def test_drawer_puts_true_points_are_the_object_and_the_drawer_floor_and_replace_the_head_in_its_middle_cycle(
        run, tmp_path):
    from types import SimpleNamespace

    from datagen.views_stages import drop_point
    from policy.oracle_eval import DrawerPutPoints
    from sim.tasks.drawer import CABINET

    ep = build_episode("drawer_put", SEED, "heavy", "fast")
    state = StateView(ep.world)
    truth = DrawerPutPoints(OFFSETS, 0.0, SEED, "drawer_put")
    truth(ep.world, ep.instance)
    R = state.rotation(CABINET)
    np.testing.assert_allclose(truth.points[0], state.position(ep.instance.params["target"]) + R @ OFFSETS["grasp"])
    np.testing.assert_allclose(truth.points[1], drop_point(SimpleNamespace(world=ep.world)) + R @ OFFSETS["release"])
    model, _, _ = load_run_model(run)
    policy = OracleAuxPolicy(model, source_normalizer(run), hash_embedder, only_stage=1)
    policy.truth = truth
    cfg = model.cfg
    images, proprio = _observation(cfg, ep)
    emb = policy.embed("open the drawer")
    opening, taking = policy.cond(images, proprio, emb, stage=0), policy.cond(images, proprio, emb, stage=1)
    torch.testing.assert_close(taking[0, -AUX_DIM:], relative_to_tcp(truth.points, proprio[-1]))
    torch.testing.assert_close(opening[0, :-AUX_DIM], taking[0, :-AUX_DIM])
    assert not torch.allclose(opening[0, -AUX_DIM:], taking[0, -AUX_DIM:])  # the head's own while opening
    with pytest.raises(ValueError, match="'pick_place' is run as one command"):
        oracle_eval(run, tmp_path / "ev", episodes=1, task="pick_place", phases=True, progress=False)


def test_the_oracle_policy_carries_the_runs_gripper_levels_to_the_controller(run):
    from policy.oracle_eval import _WORKER, _init

    _init({"run": str(run), "steps": None, "true_points": "both", "task": "pick_place",
           "gripper_levels": [0.0, 0.5, 1.0]})
    assert _WORKER["policy"].manifest["data"] == {"gripper_levels": [0.0, 0.5, 1.0]}
