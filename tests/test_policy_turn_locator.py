"""The turn locator (policy/goal_locator.py, the "turn" question): taught on views along the way to the grasp with
the turn label in the head's grasp-axis slot, checked on recorded frames before the first close
(policy.turn_query_measure), exported as turn_locator.onnx, read by the bundle, and kept by a later export."""

import json

import numpy as np
import pytest
import torch

from datagen.store import ShardWriter
from datagen.workers import synthetic_episode
from policy.bundle import Bundle
from policy.export import export
from policy.testing import SHIPPED_LIKE, STACK, TINY, hash_embedder, random_observation, smooth_episode
from policy.turn_query import TurnQuery
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()
AXIS = {**SHIPPED_LIKE, "aux_grasp_axis": True}
BLOCK = {"shape": "block", "size": [0.02, 0.02, 0.02]}


def _stack_data(root, episodes: int = 4):
    """Smooth synthetic stack episodes (successful, one close) whose task records name two square blocks."""
    record = {"family": "stack", "params": {"top": "a", "bottom": "b"},
              "objects": [{"name": "a", **BLOCK}, {"name": "b", **BLOCK}]}
    with ShardWriter(root, "w0") as w:
        for seed in range(episodes):
            ep = synthetic_episode("stack", seed, steps=20)
            smooth_episode(ep, seed)
            ep.meta.update(success=True, instruction=STACK, task_record=record,
                           label={"success": True, "source": "synthetic"})
            w.append(ep)
    return root


@pytest.fixture(scope="module")
def turned(tmp_path_factory):
    from datagen.views import generate
    from policy.pretrain import pretrain
    from policy.train import train

    root = tmp_path_factory.mktemp("turn_locator")
    data = _stack_data(root / "data")
    train(data, dict(TINY), root / "run", steps=4, embedder=hash_embedder, progress=False, threads=1, overrides=AXIS)
    export(root / "run", root / "plain", cache_dir=CACHE)
    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    generate(root / "views", range(510, 513), 3, offsets, progress=False, image_size=tuple(TINY["image_size"]),
             task="stack")
    settings = {"lr": 3e-3, "warmup_steps": 1, "val_every": 2, "log_every": 2}
    summary = pretrain(root / "views", data, root / "plain", root / "turn", 4, settings, threads=1, progress=False,
                       embedder=hash_embedder, init_from=root / "plain", goal_locator=True, locator_question="turn")
    export(root / "plain", root / "bundle", cache_dir=CACHE, turn_locator=root / "turn")
    return root, data, summary


def test_pretraining_a_turn_locator_trains_the_axis_slot_on_turn_labels_and_checks_it_before_the_close(turned):
    from policy.bundle_import import model_from_bundle
    from policy.train import load_run_model

    root, _, s = turned
    pre = json.loads((root / "turn" / "dataset.json").read_text())["pretrain"]
    assert pre["locator_question"] == "turn" and "look_m" not in pre and s["views"] == 9  # all three of each scene
    assert pre["period_deg"] == pytest.approx(90.0) and pre["families"] == ["stack"]
    rows = [json.loads(x) for x in (root / "turn" / "metrics.jsonl").read_text().splitlines()]
    checks = [r for r in rows if "turn_deg_median" in r]
    assert [r["step"] for r in checks] == [0, 2, 4] and s["validation"]["step"] == 4
    assert all(0.0 <= r["turn_deg_median"] <= 45.0 and 0.0 <= r["sure_share"] <= 1.0 for r in checks)
    # the synthetic episodes never turn the wrist: not turning is exactly right on them
    assert all(r["no_turn_deg_median"] == 0.0 for r in checks)
    src, _, _ = model_from_bundle(root / "plain")
    loc, _, _ = load_run_model(root / "turn", ema=False)
    w0, w1 = src.aux_head[-1].weight, loc.aux_head[-1].weight
    assert (w1[6:] - w0[6:]).abs().max() > 1e-4  # the axis slot learnt
    torch.testing.assert_close(w1[:6], w0[:6], rtol=1e-5, atol=1e-7)  # the points had no loss


def test_the_export_ships_the_turn_locator_and_the_bundle_asks_it(turned):
    from policy.parity import STEP_TOL

    root, _, _ = turned
    m = json.loads((root / "bundle" / "manifest.json").read_text())
    q = m["turn_query"]
    assert q["families"] == ["stack"] and q["period_deg"] == pytest.approx(90.0) and q["min_norm"] == 0.5
    assert q["locator_from"]["locator_question"] == "turn" and "turn_deg_median" in q["measured"]
    assert "turn_locator.onnx" in m["files"] and m["parity"]["turn_locator_max_abs_err"] <= STEP_TOL
    b = Bundle.load(root / "bundle")
    images, proprio = random_observation(b)
    label = b.turn_label(images, proprio, b.embed(STACK))
    assert label.shape == (2,) and np.all(np.isfinite(label))
    query = TurnQuery(b, STACK, "stack")
    query.ask(images, proprio)
    assert query.asked == 1 and (query.turn is None or abs(query.turn) <= np.pi / 4)
    kept = export(root / "run", root / "kept", cache_dir=CACHE, queries_from=root / "bundle")
    assert kept["turn_query"]["kept_from"]["bundle"] == str(root / "bundle")
    assert kept["files"]["turn_locator.onnx"] == m["files"]["turn_locator.onnx"]


def test_a_turn_locator_is_refused_where_it_does_not_fit(turned):
    from policy.bundle import BundleError

    root, data, _ = turned
    with pytest.raises(ValueError, match="taught the turn question, asked here the goal question"):
        export(root / "plain", root / "y", cache_dir=CACHE, goal_locator=root / "turn",
               goal_query={"families": ["stack"], "data": data, "ticks": 2})
    broken = json.loads((root / "bundle" / "manifest.json").read_text())
    broken["turn_query"]["period_deg"] = 0
    (root / "broken").mkdir()
    for f in (root / "bundle").iterdir():
        if f.name != "manifest.json":
            (root / "broken" / f.name).symlink_to(f)
    (root / "broken" / "manifest.json").write_text(json.dumps(broken))
    with pytest.raises(BundleError, match="turn_query.period_deg"):
        Bundle.load(root / "broken")
