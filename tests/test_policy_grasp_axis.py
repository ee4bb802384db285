"""The grasp-axis aux target (policy.grasp_axis, `aux_grasp_axis`): labels on recorded episodes and on rendered
views, the head and the denoiser's conditioning two wider, exported with parity."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from datagen.store import ShardWriter
from datagen.workers import synthetic_episode
from policy.config import load_policy_config
from policy.grasp_axis import angle_error_deg, axis_label, episode_target_has_axis, has_axis
from policy.normalize import Normalizer
from policy.testing import TINY, hash_embedder, smooth_episode
from runtime.bench_runtime import test_cache_dir as cache_dir
from sim.config import ConfigError

AXIS = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "aux_grasp_axis": True}
BAR = {"shape": "bar", "size": [0.047, 0.019, 0.019]}
SHAPES = (BAR, {"shape": "cylinder", "size": [0.021, 0.023]}, {"shape": "block", "size": [0.02, 0.02, 0.02]})


def _record(target: dict) -> dict:
    objects = [{"name": "obj0", **target}, {"name": "obj1", "shape": "cylinder", "size": [0.02, 0.02]}]
    return {"params": {"target": "obj0", "bin": "bin_left"}, "objects": objects}


def _turn(rot6d: np.ndarray, yaw: float) -> np.ndarray:
    """rot6d rows turned by `yaw` about the base's vertical."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return np.concatenate([rot6d[:, :3] @ Rz.T, rot6d[:, 3:6] @ Rz.T], axis=1)


def test_the_label_is_the_doubled_yaw_difference_and_zero_without_one_axis():
    np.testing.assert_allclose(axis_label(0.3, 0.3, True), [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(axis_label(0.3 + np.pi, 0.3, True), [1.0, 0.0], atol=1e-6)  # a half turn: same
    np.testing.assert_allclose(axis_label(0.3 + np.pi / 2, 0.3, True), [-1.0, 0.0], atol=1e-6)  # across
    np.testing.assert_allclose(axis_label(0.3 + np.pi / 4, 0.3, True), [0.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(axis_label([0.1, 0.2], [0.0, 0.0], [True, False])[1], [0.0, 0.0])
    assert [has_axis(SimpleNamespace(**o)) for o in SHAPES] == [True, False, False]
    assert angle_error_deg(axis_label(0.5, 0.0, True), axis_label(0.2, 0.0, True)) == pytest.approx(
        np.degrees(0.3), abs=1e-4)
    assert angle_error_deg(axis_label(np.pi / 2, 0.0, True), axis_label(0.0, 0.0, True)) == pytest.approx(90.0)
    assert [episode_target_has_axis({"task_record": _record(o)}) for o in SHAPES] == [True, False, False]
    with pytest.raises(ValueError, match="task_record"):
        episode_target_has_axis({"seed": 3})


def test_other_families_label_the_object_they_pick_up():
    bar, block = (dict(_record(o)["objects"][0], name=n) for o, n in ((SHAPES[0], "a"), (SHAPES[1], "b")))
    stack = {"family": "stack", "params": {"top": "a", "bottom": "b"}, "objects": [bar, block]}
    assert episode_target_has_axis({"task_record": stack})
    assert not episode_target_has_axis({"task_record": {**stack, "params": {"top": "b", "bottom": "a"}}})
    drawer_put = {"family": "drawer_put", "params": {"target": "a", "cabinet": {}}, "objects": [bar]}
    assert episode_target_has_axis({"task_record": drawer_put})
    # the handle is no object with a footprint: no axis to name
    assert not episode_target_has_axis({"task_record": {"family": "drawer_open", "params": {}, "objects": []}})


def test_the_axis_needs_the_tcp_frames_aux_head():
    with pytest.raises(ConfigError, match="aux_grasp_axis needs aux_target_weight > 0 and aux_target_frame 'tcp'"):
        load_policy_config(TINY, {"aux_grasp_axis": True, "aux_target_weight": 1.0})
    plain = load_policy_config(TINY, {**AXIS, "aux_grasp_axis": False, "aux_condition": True})
    cfg = load_policy_config(TINY, {**AXIS, "aux_condition": True})
    assert (plain.aux_dim, cfg.aux_dim) == (6, 8) and cfg.global_cond_dim == plain.global_cond_dim + 2


@pytest.fixture(scope="module")
def axis_data(tmp_path_factory):
    """Two bar episodes and a cylinder one whose TCP is turned off the recorded grasp yaw (0) by `turns`."""
    root = tmp_path_factory.mktemp("axis") / "data"
    turns = (0.4, -1.0, 0.7)
    with ShardWriter(root, "w0") as w:
        for seed, (turn, target) in enumerate(zip(turns, (BAR, BAR, SHAPES[1]))):
            ep = synthetic_episode("pick_place", seed, steps=24)
            smooth_episode(ep, seed)
            ep.proprio[:, 3:9] = _turn(ep.proprio[:, 3:9], turn)
            ep.meta.update(success=True, check_success=True, task_record=_record(target))
            ep.meta["label"]["success"] = True
            w.append(ep)
    return root, turns


def test_recorded_episodes_label_the_axis_relative_to_the_tcp(axis_data):
    from policy.data import PolicyDataset

    root, turns = axis_data
    ds = PolicyDataset(root, load_policy_config(TINY, AXIS), train=False, embedder=hash_embedder)
    points = PolicyDataset(root, load_policy_config(TINY, {**AXIS, "aux_grasp_axis": False}), train=False,
                           embedder=hash_embedder)
    seen = set()
    for i in range(len(ds)):
        k = ds.index[i][0]
        aux = ds.aux_target(i).numpy()
        assert aux.shape == (8,)
        np.testing.assert_array_equal(aux[:6], points.aux_target(i).numpy())
        want = axis_label(0.0, turns[k], k < 2)  # the grasp yaw is 0, the TCP turned by turns[k]
        np.testing.assert_allclose(aux[6:], want, atol=1e-5)
        seen.add(k)
    assert seen == {0, 1, 2}


def test_views_keep_the_grasp_yaw_and_pretraining_labels_the_axis(axis_data, tmp_path):
    from datagen.views import generate, load
    from policy.pretrain import Views, pretrain
    from policy.train import load_run_model, train
    from sim.build import build_episode
    from sim.state import StateView
    from sim.tasks.pick_place import footprint_period, grasp_yaw

    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    views = tmp_path / "views"
    generate(views, range(300, 302), 3, offsets, progress=False, image_size=(32, 32))
    v = load(views)
    for seed in (300, 301):
        ep = build_episode("pick_place", seed, "heavy", "fast")
        o = ep.instance.obj(ep.instance.params["target"])
        rows = v["seed"] == seed
        np.testing.assert_allclose(v["grasp_yaw"][rows], grasp_yaw(o, StateView(ep.world).rotation(o.name)),
                                   atol=1e-6)
        np.testing.assert_allclose(v["footprint_period"][rows], footprint_period(o) or 0.0)
    root, _ = axis_data
    cfg = load_policy_config(TINY, AXIS)
    norm = Normalizer.fit(v["proprio"], np.zeros((4, cfg.action_dim), np.float32))
    aux = Views(views, cfg, norm, hash_embedder).aux.numpy()
    tcp_yaw = np.arctan2(v["proprio"][:, 4], v["proprio"][:, 3])
    np.testing.assert_allclose(aux[:, 6:], axis_label(v["grasp_yaw"], tcp_yaw, v["footprint_period"] > 3.0),
                               atol=1e-5)

    over = {**AXIS, "lr": 3e-3, "warmup_steps": 1, "log_every": 5, "color_jitter": 0.0}
    s = pretrain(views, root, dict(TINY), tmp_path / "pre", 2, over, threads=1, progress=False,
                 embedder=hash_embedder)
    head = torch.load(s["checkpoint"], weights_only=False)["ema"]["model"]["aux_head.2.weight"]
    assert head.shape[0] == 8
    run = tmp_path / "run"
    train(root, dict(TINY), run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides={**AXIS, "aux_condition": True, "freeze_pretrained": True}, init_from=tmp_path / "pre")
    model, _, _ = load_run_model(run)
    torch.testing.assert_close(model.aux_head[2].weight, head)
    cache = cache_dir()
    from policy.export import export

    m = export(run, tmp_path / "bundle", cache_dir=cache)
    assert m["parity"]["chunk_max_abs_err"] <= 1e-4 and m["dims"]["global_cond"] == model.cfg.global_cond_dim

    old = tmp_path / "old_views"
    old.mkdir()
    shard = dict(np.load(next(views.glob("views_*.npz"))))
    np.savez(old / "views_00000300.npz", **{k: x for k, x in shard.items() if k not in ("grasp_yaw",)})
    with pytest.raises(ValueError, match="rendered before it was kept"):
        Views(old, cfg, norm, hash_embedder)


def test_validation_reports_the_axis_error_where_the_gripper_is_still_turned_off(axis_data):
    from policy.data import PolicyDataset
    from policy.model import DiffusionPolicy
    from policy.validate import Validator

    root, turns = axis_data
    cfg = load_policy_config(TINY, AXIS)
    ds = PolicyDataset(root, cfg, train=False, embedder=hash_embedder)
    model = DiffusionPolicy(cfg)
    with torch.no_grad():  # a head that always answers "no turn": off by exactly the TCP's turn
        model.aux_head[2].weight.zero_()
        model.aux_head[2].bias.copy_(torch.tensor([0, 0, 0, 0, 0, 0, 1.0, 0]))
    out = Validator(ds, ds, chunks=False)(model, "cpu")
    bars = np.degrees(np.abs(turns[:2]))  # both bar episodes are turned 20 degrees or more off; the cylinder's
    assert min(abs(out["val_axis_deg"] - b) for b in (*bars, bars.mean())) < 1e-3  # label is (0, 0): left out
    assert out["guess_axis_deg"] == pytest.approx(out["val_axis_deg"], abs=1e-3)
    plain = load_policy_config(TINY, {**AXIS, "aux_grasp_axis": False})
    ds = PolicyDataset(root, plain, train=False, embedder=hash_embedder)
    assert "val_axis_deg" not in Validator(ds, ds, chunks=False)(DiffusionPolicy(plain), "cpu")
