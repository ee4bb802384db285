"""The goal locator (policy/goal_locator.py): its views, its pretraining (the swapped command, the release point as
the grasp label, the loss on that point alone), its export as goal_locator.onnx, parity and the bundle's
goal_point, and the refusals."""

import json
import shutil

import numpy as np
import pytest
import torch

from policy.action_frame import points_from_tcp
from policy.bundle import Bundle, BundleError
from policy.config import AUX_TCP_SCALE
from policy.export import export
from policy.goal_locator import locator_rows
from policy.goal_query import GoalQuery
from policy.model import prepare_images
from policy.normalize import Normalizer
from policy.parity import STEP_TOL
from policy.testing import STACK, TINY, goal_query_run, hash_embedder, random_observation
from policy.train import load_run_model
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()


def test_locator_rows_keep_each_scenes_home_view_with_the_swapped_command_and_the_release_as_grasp():
    n = 7
    v = {"seed": np.array([1, 1, 1, 2, 2, 3, 3]), "task": np.array(["stack"] * 5 + ["pick_place"] * 2),
         "stage": np.array([""] * n),
         "instruction": np.array([STACK] * 3 + ["place the green block onto the white block"] * 2
                                 + ["put the red cube in the blue bin"] * 2),
         "points": np.arange(n * 6, dtype=np.float32).reshape(n, 2, 3), "scene": np.zeros((n, 4, 4, 3), np.uint8)}
    out = locator_rows(v)
    assert out["seed"].tolist() == [1, 2]  # first views only; pick_place's command names no second object
    assert out["instruction"].tolist() == ["stack the blue block on the red block",
                                           "place the white block onto the green block"]
    np.testing.assert_array_equal(out["points"][:, 0], v["points"][[0, 3], 1])
    np.testing.assert_array_equal(out["points"][:, 1], v["points"][[0, 3], 1])
    assert out["scene"].shape == (2, 4, 4, 3)
    with pytest.raises(ValueError, match="two objects"):
        locator_rows({**v, "instruction": np.array(["open the drawer"] * n)})


@pytest.fixture(scope="module")
def located(tmp_path_factory, loose_offsets):
    from datagen.views import generate
    from policy.pretrain import pretrain

    root = tmp_path_factory.mktemp("goal_locator")
    data, _ = goal_query_run(root)
    export(root / "run", root / "plain", cache_dir=CACHE)
    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    generate(root / "views", range(500, 503), 2, offsets, progress=False, image_size=tuple(TINY["image_size"]),
             task="stack")
    summary = pretrain(root / "views", data, root / "plain", root / "locator", 6,
                       {"lr": 3e-3, "warmup_steps": 1, "val_every": 3, "log_every": 3}, threads=1, progress=False,
                       embedder=hash_embedder, init_from=root / "plain", goal_locator=True)
    export(root / "plain", root / "bundle", cache_dir=CACHE, goal_locator=root / "locator",
           goal_query={"families": ["stack"], "data": data, "ticks": 2})
    return root, summary


def test_pretraining_a_locator_trains_only_its_goal_point_on_home_views(located):
    root, s = located
    assert s["views"] == 3 and s["scenes"] == 3  # one home view of each stack scene
    rows = [json.loads(x) for x in (root / "locator" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "goal_cm_median" in r] == [0, 3, 6]
    assert s["goal_query_before"]["step"] == 0 and s["validation"]["step"] == 6
    assert json.loads((root / "locator" / "dataset.json").read_text())["pretrain"]["goal_locator"] is True
    from policy.bundle_import import model_from_bundle

    src, _, _ = model_from_bundle(root / "plain")
    loc, _, _ = load_run_model(root / "locator", ema=False)
    w0, w1 = src.aux_head[-1].weight, loc.aux_head[-1].weight
    assert (w1[:3] - w0[:3]).abs().max() > 1e-4  # the goal point's outputs learnt
    torch.testing.assert_close(w1[3:], w0[3:], rtol=1e-5, atol=1e-7)  # the rest had no loss (weight decay only)
    moved = lambda part: max(float((a - b).detach().abs().max()) for a, b in zip(  # noqa: E731
        loc.get_submodule(part).parameters(), src.get_submodule(part).parameters()))
    assert moved("obs_encoder.images") > 1e-5  # the encoders learnt the question too
    assert moved("unet") == 0.0 and moved("obs_encoder.proprio") == 0.0  # what the query does not read: untouched


def test_the_exported_locator_answers_the_goal_query_in_place_of_the_head(located):
    root, _ = located
    m = json.loads((root / "bundle" / "manifest.json").read_text())
    q = m["goal_query"]
    assert q["locator"] is True and q["locator_from"]["goal_locator"] is True and q["locator_from"]["scenes"] == 3
    assert m["graphs"]["goal_locator"]["file"] == "goal_locator.onnx" and "goal_locator.onnx" in m["files"]
    assert m["parity"]["goal_locator_max_abs_err"] <= STEP_TOL
    b = Bundle.load(root / "bundle")
    images, proprio = random_observation(b, 1)
    emb = b.embed("stack the blue block on the red block")
    loc, _, _ = load_run_model(root / "locator")
    cfg = loc.cfg
    with torch.no_grad():
        imgs = {c: prepare_images(torch.from_numpy(images[c])[None], cfg.crop_size) for c in cfg.cameras}
        feats = loc.obs_encoder.camera_features(imgs, torch.from_numpy(emb)[None])[:, -1]
        rel = loc.aux_head(feats)[0, :3].numpy()
    want = points_from_tcp(rel[None] * AUX_TCP_SCALE, proprio[-1, :9].astype(np.float64))[0]
    np.testing.assert_allclose(b.goal_point(images, proprio, emb), want, atol=2e-4)
    assert np.abs(b.goal_point(images, proprio, emb) - b.grasp_point(images, proprio, emb)).max() > 1e-4
    query = GoalQuery(b, STACK, "stack")  # the runtime's query reads the locator
    release = query.release(images, proprio)
    np.testing.assert_allclose(release[:3], b.goal_point(images, proprio, emb) + np.asarray(q["offset_m"]), atol=1e-5)


def test_a_bundle_whose_manifest_asks_a_locator_it_lacks_is_refused(located, tmp_path):
    root, _ = located
    broken = tmp_path / "broken"
    shutil.copytree(root / "bundle", broken)
    m = json.loads((broken / "manifest.json").read_text())
    del m["graphs"]["goal_locator"]
    (broken / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="goal_locator"):
        Bundle.load(broken)
    m["goal_query"]["locator"] = "yes"
    (broken / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="goal_query.locator"):
        Bundle.load(broken)


def test_export_refuses_a_locator_without_the_query_or_a_run_that_is_no_locator(located, tmp_path):
    root, _ = located
    with pytest.raises(ValueError, match="--goal-query"):
        export(root / "plain", tmp_path / "x", cache_dir=CACHE, goal_locator=root / "locator")
    with pytest.raises(ValueError, match="not a goal locator"):
        export(root / "plain", tmp_path / "y", cache_dir=CACHE, goal_locator=root / "run",
               goal_query={"families": ["stack"], "data": root / "data", "ticks": 2})
    with pytest.raises(ValueError, match="--goal-locator RUN again"):  # the query would be lost silently
        export(root / "bundle", tmp_path / "z", cache_dir=CACHE, pace={"stack": 0.5})
    assert not any((tmp_path / d).exists() for d in ("x", "y", "z"))


def test_the_policy_bench_times_a_goal_query_bundle_and_its_goal_point(located):
    from policy.bench import format_table, run_policy_bench

    root, _ = located
    f = run_policy_bench(quick=True, bundle=root / "bundle", threads=(1,))
    assert f["goal_point"]["p50_ms"] > 0 and f["obs_encoder"]["p50_ms"] > 0
    assert f["bytes"]["goal_locator.onnx"] > 0 and "goal_point" in format_table(f)


def test_a_locator_of_the_whole_frame_is_exported_measured_and_kept_at_its_own_crop(located, tmp_path):
    """A locator may read the whole frame where the policy reads its centre crop: the wrist camera shows the block
    to stack on at its edge in many scenes, which the centre crop cuts off. Its crop is its graph's and the
    manifest's record, so the bundle's goal point, the measured table and a re-export that keeps it all read it."""
    from policy.bundle_import import locator_from_bundle
    from policy.pretrain import pretrain

    root, _ = located
    whole = list(TINY["image_size"])
    data = root / "data"
    pretrain(root / "views", data, root / "plain", tmp_path / "whole", 3,
             {"lr": 3e-3, "warmup_steps": 1, "val_every": 3, "log_every": 3, "crop_size": whole}, threads=1,
             progress=False, embedder=hash_embedder, init_from=root / "plain", goal_locator=True)
    export(root / "plain", tmp_path / "bundle", cache_dir=CACHE, goal_locator=tmp_path / "whole",
           goal_query={"families": ["stack"], "data": data, "ticks": 2})
    m = json.loads((tmp_path / "bundle" / "manifest.json").read_text())
    assert m["goal_query"]["locator_from"]["crop_size"] == whole and m["crop_size"] == TINY["crop_size"]
    assert m["parity"]["goal_locator_max_abs_err"] <= STEP_TOL
    b = Bundle.load(tmp_path / "bundle")
    images, proprio = random_observation(b, 1)
    emb = b.embed("stack the blue block on the red block")
    loc, _, _ = load_run_model(tmp_path / "whole")
    with torch.no_grad():
        def asked(crop):
            imgs = {c: prepare_images(torch.from_numpy(images[c])[None], crop) for c in loc.cfg.cameras}
            rel = loc.aux_head(loc.obs_encoder.camera_features(imgs, torch.from_numpy(emb)[None])[:, -1])[0, :3]
            return points_from_tcp(rel.numpy()[None] * AUX_TCP_SCALE, proprio[-1, :9].astype(np.float64))[0]
        whole_answer, centre_answer = asked(tuple(whole)), asked(tuple(TINY["crop_size"]))
    assert np.abs(whole_answer - centre_answer).max() > 1e-4  # the two crops tell apart
    np.testing.assert_allclose(b.goal_point(images, proprio, emb), whole_answer, atol=2e-4)
    rebuilt, record = locator_from_bundle(tmp_path / "bundle", "goal_locator")
    assert list(rebuilt.cfg.crop_size) == whole and record["rebuilt_max_abs_err"] <= STEP_TOL
    kept = export(root / "plain", tmp_path / "kept", cache_dir=CACHE, queries_from=tmp_path / "bundle")
    assert kept["goal_query"]["locator_from"]["crop_size"] == whole
    assert (tmp_path / "kept" / "goal_locator.onnx").read_bytes() == (tmp_path / "bundle" / "goal_locator.onnx").read_bytes()
    with pytest.raises(ValueError, match="asks no object query or turn query to keep"):  # the goal query measured anew
        export(root / "plain", tmp_path / "x", cache_dir=CACHE, queries_from=tmp_path / "bundle",
               goal_locator=tmp_path / "whole", goal_query={"families": ["stack"], "data": data, "ticks": 2})


def test_a_locator_goes_on_from_a_bundles_own_locator(located, tmp_path):
    """--from-locator: the run starts from the bundle's goal locator (rebuilt from its graph), not from its policy's
    head, so its error before training is the shipped locator's."""
    from policy.bundle_import import locator_from_bundle
    from policy.goal_query_measure import measure
    from policy.pretrain import pretrain

    root, _ = located
    data, settings = root / "data", {"lr": 3e-3, "warmup_steps": 1, "val_every": 1, "log_every": 1}
    go = lambda out, **kw: pretrain(root / "views", data, root / "bundle", tmp_path / out, 1, settings,  # noqa: E731
                                    threads=1, progress=False, embedder=hash_embedder, init_from=root / "bundle",
                                    goal_locator=True, **kw)
    went_on, afresh = go("on", from_locator=True), go("afresh")
    shipped, _ = locator_from_bundle(root / "bundle", "goal_locator")
    want = measure(shipped, Normalizer.load(root / "bundle" / "stats.npz"), data, ["stack"],
                   embedder=hash_embedder)["measured"]["release_cm_median"]
    assert went_on["goal_query_before"]["goal_cm_median"] == pytest.approx(want, abs=0.02)
    assert afresh["goal_query_before"]["goal_cm_median"] != pytest.approx(want, abs=0.02)
    record = json.loads((tmp_path / "on" / "warm_start.json").read_text())
    assert record["locator"] == "goal_locator" and record["rebuilt_max_abs_err"] <= STEP_TOL
    with pytest.raises(ValueError, match="from_locator"):
        pretrain(root / "views", data, root / "bundle", tmp_path / "x", 1, settings, threads=1, progress=False,
                 embedder=hash_embedder, init_from=root / "bundle", from_locator=True)
    with pytest.raises(ValueError, match="from_locator"):  # a pretrain run has no locator graph to go on from
        pretrain(root / "views", data, root / "bundle", tmp_path / "y", 1, settings, threads=1, progress=False,
                 embedder=hash_embedder, init_from=tmp_path / "on", goal_locator=True, from_locator=True)


def test_a_locator_taught_from_a_look_pose_is_measured_there_and_its_pose_shipped(located, tmp_path):
    """`sudd views --look`: the locator learns the view from the look pose; the export measures it on each
    episode's scene rendered from there (the recordings never stood there) and the manifest names the pose, which
    the runtime moves to before asking (runtime/look.py). A locator of mixed poses is refused."""
    from datagen.views import generate
    from policy.pretrain import pretrain

    root, _ = located
    look = (0.15, 0.08, 0.1)
    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    generate(tmp_path / "views", range(503, 506), 1, offsets, progress=False, image_size=tuple(TINY["image_size"]),
             task="stack", look=look)
    settings = {"lr": 3e-3, "warmup_steps": 1, "val_every": 2, "log_every": 2}
    summary = pretrain(tmp_path / "views", root / "data", root / "plain", tmp_path / "locator", 2, settings,
                       threads=1, progress=False, embedder=hash_embedder, init_from=root / "plain", goal_locator=True)
    assert json.loads((tmp_path / "locator" / "dataset.json").read_text())["pretrain"]["look_m"] == list(look)
    assert summary["goal_query_before"]["goal_cm_median"] > 0 and summary["look_m"] == list(look)
    table = export(root / "plain", tmp_path / "bundle", cache_dir=CACHE, goal_locator=tmp_path / "locator",
                   goal_query={"families": ["stack"], "data": root / "data", "ticks": 2})["goal_query"]
    assert table["look_m"] == list(look) and table["locator_from"]["look_m"] == list(look)
    home = json.loads((root / "bundle" / "manifest.json").read_text())["goal_query"]
    assert "look_m" not in home and table["measured"]["episodes"] == home["measured"]["episodes"]  # the same ones
    assert Bundle.load(tmp_path / "bundle").goal_query.look_m == look
    kept = export(root / "plain", tmp_path / "kept", cache_dir=CACHE, queries_from=tmp_path / "bundle")
    assert kept["goal_query"]["look_m"] == list(look)  # a later denoiser keeps asking from where it was taught
    with pytest.raises(ValueError, match="2 poses"):
        pretrain([tmp_path / "views", root / "views"], root / "data", root / "plain", tmp_path / "mixed", 1, settings,
                 threads=1, progress=False, embedder=hash_embedder, init_from=root / "plain", goal_locator=True)
