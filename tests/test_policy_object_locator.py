"""The object locator (policy/goal_locator.py, the "object" question): drawer_put's object and where in the drawer
it goes, taught from the start on at-home views of the object stage, scored on recorded episodes' first frames
against their middle grasp cycle (policy.goal_query_measure.measure_object), and asked in `sudd oracle-eval
--points-from` (policy.oracle_eval.LocatedPoints) in place of the truth."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from datagen.store import ShardWriter
from datagen.workers import synthetic_episode
from policy.action_frame import points_from_tcp
from policy.config import AUX_TCP_SCALE
from policy.export import export
from policy.goal_locator import load_locator, locator_rows
from policy.testing import SHIPPED_LIKE, TINY, hash_embedder, smooth_episode
from policy.train import load_run_model
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()
CLOSED = ((3, 8), (12, 17), (21, 26))  # drawer_put's three grasp cycles: the handle, the object, the handle again
COMMAND = "put the red block in the drawer"


def _drawer_put_data(root, episodes: int = 4, stows: int = 0):
    """Smooth synthetic drawer_put episodes (all successful) that close the gripper three times, then `stows`
    drawer_stow episodes that close it once (drawer_put's middle cycle's steps)."""
    with ShardWriter(root, "w0") as w:
        for seed in range(episodes + stows):
            task = "drawer_put" if seed < episodes else "drawer_stow"
            ep = synthetic_episode(task, seed, steps=30)
            smooth_episode(ep, seed)
            grip = np.zeros(len(ep.action), np.float32)
            for a, b in CLOSED if task == "drawer_put" else CLOSED[1:2]:
                grip[a:b] = 1.0
            ep.action[:, -1], ep.proprio[:, 9] = grip, np.roll(grip, 1)
            ep.meta.update(success=True, instruction=COMMAND, label={"success": True, "source": "synthetic"})
            w.append(ep)
    return root


def test_object_rows_keep_each_scenes_first_at_home_view_of_a_later_stage_as_labelled():
    n = 8
    v = {"seed": np.array([1, 1, 2, 2, 3, 3, 4, 4]), "task": np.array(["drawer_put"] * 6 + ["drawer_stow"] * 2),
         "stage": np.array(["object", "object", "object", "object", "", "", "", ""]),
         "at_home": np.array([True, True, False, False, False, False, True, True]),
         "instruction": np.array([COMMAND] * n), "points": np.arange(n * 6, dtype=np.float32).reshape(n, 2, 3)}
    out = locator_rows(v, "object")
    # drawer_put's object stage at home, and drawer_stow's first grasp at home (its object where it starts)
    assert out["seed"].tolist() == [1, 4] and out["instruction"].tolist() == [COMMAND] * 2  # the command as it is
    np.testing.assert_array_equal(out["points"], v["points"][[0, 6]])  # the object and the drop, not swapped
    with pytest.raises(ValueError, match="--at-home"):
        locator_rows({**v, "at_home": np.zeros(n, bool)}, "object")
    with pytest.raises(ValueError, match="expected one of goal, object"):
        locator_rows(v, "lid")


def test_a_locator_is_asked_only_the_question_it_was_taught(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"pretrain": {"goal_locator": True,
                                                                    "locator_question": "object"}}))
    with pytest.raises(ValueError, match="taught the object question, asked here the goal question"):
        load_locator(tmp_path, SimpleNamespace(), "goal")


@pytest.fixture(scope="module")
def object_located(tmp_path_factory):
    from datagen.views import generate
    from policy.pretrain import pretrain
    from policy.train import train

    root = tmp_path_factory.mktemp("object_locator")
    data = _drawer_put_data(root / "data", stows=2)
    train(data, dict(TINY), root / "run", steps=4, embedder=hash_embedder, progress=False, threads=1,
          overrides=SHIPPED_LIKE)
    export(root / "run", root / "plain", cache_dir=CACHE)
    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.1])}
    size = tuple(TINY["image_size"])
    generate(root / "views", range(700, 703), 2, offsets, progress=False, image_size=size, task="drawer_put",
             stage="object", at_home=True)
    generate(root / "views", range(700, 702), 2, offsets, progress=False, image_size=size, task="drawer_put",
             stage="object")  # on the way from the handle: not the question's views
    generate(root / "views", range(710, 712), 1, offsets, progress=False, image_size=size, task="drawer_stow",
             at_home=True)  # drawer_stow's object from its start: the drawer open, the same question
    summary = pretrain(root / "views", data, root / "plain", root / "locator", 6,
                       {"lr": 3e-3, "warmup_steps": 1, "val_every": 3, "log_every": 3}, threads=1, progress=False,
                       embedder=hash_embedder, init_from=root / "plain", goal_locator=True,
                       locator_question="object")
    return root, data, summary


def test_pretraining_an_object_locator_trains_the_grasp_and_release_points_on_at_home_views(object_located):
    root, _, s = object_located
    assert s["views"] == 5 and s["scenes"] == 5  # the first at-home view of each scene, nothing else
    pre = json.loads((root / "locator" / "dataset.json").read_text())["pretrain"]
    assert pre["goal_locator"] is True and pre["locator_question"] == "object"
    rows = [json.loads(x) for x in (root / "locator" / "metrics.jsonl").read_text().splitlines()]
    checks = [r for r in rows if "object_grasp_cm_median" in r]
    assert [r["step"] for r in checks] == [0, 3, 6] and s["validation"]["step"] == 6
    assert all(np.isfinite(r["object_drawer_stow_grasp_cm_median"]) for r in checks)  # each family measured
    assert all(np.isfinite(r["object_release_cm_p75"]) for r in checks)
    from policy.bundle_import import model_from_bundle

    src, _, _ = model_from_bundle(root / "plain")
    loc, _, _ = load_run_model(root / "locator", ema=False)
    w0, w1 = src.aux_head[-1].weight, loc.aux_head[-1].weight
    assert (w1[:6] - w0[:6]).abs().max() > 1e-4  # both points learnt
    torch.testing.assert_close(w1[6:], w0[6:], rtol=1e-5, atol=1e-7)  # the grasp axis had no loss
    with pytest.raises(ValueError, match="taught the object question"):
        load_locator(root / "locator", loc.cfg, "goal")  # not a goal locator for `sudd export --goal-locator`


class _Zero(torch.nn.Module):
    """A locator stand-in whose points are all zero: the grasp at the TCP, the release at the base's origin."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg

    def obs_encoder(self, images, proprio, text):
        return torch.zeros(len(proprio), 1)

    def aux_points(self, features):
        return torch.zeros(len(features), self.cfg.aux_dim)


def test_the_object_measure_scores_the_first_frames_against_the_middle_cycle(object_located):
    from policy.goal_query_measure import measure_object
    from policy.normalize import Normalizer
    from datagen.store import Dataset

    root, data, _ = object_located
    loc, _, _ = load_run_model(root / "locator")
    norm = Normalizer.load(root / "locator" / "stats.npz")
    got = measure_object(_Zero(loc.cfg), norm, data, ticks=1, embedder=hash_embedder)
    store = Dataset(data)
    grasp, release = [], []
    for row in store.episodes():
        w = store.window(row["index"], fields=("action", "proprio"))
        (close, opened) = CLOSED[1][0], CLOSED[1][1]
        grasp.append(np.linalg.norm(w["proprio"][0, :3] - w["action"][close, :3]))  # the TCP at the first frame
        release.append(np.linalg.norm(w["action"][opened, :3]))
    assert got["episodes"] == 4
    assert got["grasp_cm_median"] == pytest.approx(100 * np.median(grasp), abs=0.01)
    assert got["release_cm_median"] == pytest.approx(100 * np.median(release), abs=0.01)


def test_drawer_stows_object_is_measured_on_its_first_and_only_cycle(object_located, tmp_path):
    from policy.goal_query_measure import measure_objects
    from policy.normalize import Normalizer
    from datagen.store import Dataset

    root, _, _ = object_located
    data = _drawer_put_data(tmp_path / "data", episodes=2, stows=3)
    loc, _, _ = load_run_model(root / "locator")
    norm = Normalizer.load(root / "locator" / "stats.npz")
    got = measure_objects(_Zero(loc.cfg), norm, data, ["drawer_put", "drawer_stow"], ticks=1,
                          embedder=hash_embedder)
    store = Dataset(data)
    grasp = {"drawer_put": [], "drawer_stow": []}
    for row in store.episodes():
        w = store.window(row["index"], fields=("action", "proprio"))
        grasp[row["task"]].append(np.linalg.norm(w["proprio"][0, :3] - w["action"][CLOSED[1][0], :3]))
    assert got["drawer_put"]["episodes"] == 2 and got["drawer_stow"]["episodes"] == 3
    for family, errors in grasp.items():
        assert got[family]["grasp_cm_median"] == pytest.approx(100 * np.median(errors), abs=0.01)
    with pytest.raises(ValueError, match="answers drawer_put, drawer_stow, not stack"):
        measure_objects(_Zero(loc.cfg), norm, data, ["stack"], ticks=1, embedder=hash_embedder)


def test_located_points_hold_the_median_of_the_first_answers_and_replace_the_middle_cycle_only(object_located):
    from policy.bundle_import import model_from_bundle
    from policy.data import relative_to_tcp
    from policy.oracle_eval import LocatedPoints, OracleAuxPolicy

    root, _, _ = object_located
    loc, _, _ = load_run_model(root / "locator")
    model, norm, _ = model_from_bundle(root / "plain")
    policy = OracleAuxPolicy(model, norm, hash_embedder, only_stage=1)
    located = LocatedPoints(loc, policy.embed(COMMAND), norm, ticks=2)
    policy.truth = located
    rng = np.random.default_rng(0)
    lo, hi = norm.proprio_min, norm.proprio_max
    obs = [({c: rng.integers(0, 256, (1, 32, 32, 3), dtype=np.uint8) for c in model.cfg.cameras},
            (lo + (hi - lo) * rng.random((1, len(lo)))).astype(np.float32)) for _ in range(3)]
    emb = policy.embed("open the drawer")
    conds = [policy.cond(images, proprio, emb, stage=0) for images, proprio in obs[:2]]
    assert len(located.answers) == 2 and located.points.shape == (2, 3)
    held = located.points.copy()
    np.testing.assert_allclose(held, np.median(np.stack(located.answers), axis=0))
    images, proprio = obs[2]
    cond = policy.cond(images, proprio, emb, stage=1)  # the middle cycle: given the held answer
    assert len(located.answers) == 2 and np.array_equal(located.points, held)  # asked no more
    start = cond.shape[1] - model.cfg.aux_dim
    np.testing.assert_allclose(cond[0, start:start + 6].numpy(), relative_to_tcp(held, proprio[-1]).numpy(),
                               atol=1e-6)
    grasp = points_from_tcp(cond[0, None, start:start + 3].numpy() * AUX_TCP_SCALE, proprio[-1, :9])[0]
    np.testing.assert_allclose(grasp, held[0], atol=1e-5)
    assert not np.allclose(conds[0][0, start:start + 6].numpy(), relative_to_tcp(held, obs[0][1][-1]).numpy())


def test_oracle_eval_takes_located_points_for_drawer_put_only(tmp_path):
    from policy.oracle_eval import oracle_eval

    with pytest.raises(ValueError, match="--points-from gives drawer_put's object"):
        oracle_eval(tmp_path, tmp_path / "out", 1, task="pick_place", points_from=tmp_path)


@pytest.fixture(scope="module")
def object_bundle(object_located):
    root, data, _ = object_located
    export(root / "plain", root / "bundle", cache_dir=CACHE,
           object_query={"families": ["drawer_put"], "data": data, "locator": root / "locator", "ticks": 2})
    return root


def test_the_export_records_the_object_query_and_its_graphs(object_bundle):
    from policy.parity import STEP_TOL

    m = json.loads((object_bundle / "bundle" / "manifest.json").read_text())
    q = m["object_query"]
    assert q["families"] == ["drawer_put", "drawer_stow"] and q["stage"] == 1 and q["ticks"] == 2
    assert q["family_stage"] == {"drawer_stow": 0}  # drawer_put's middle phase, served in its first cycle
    by_family = q["measured"]["by_family"]
    assert by_family["drawer_put"]["episodes"] == 4 and by_family["drawer_stow"]["episodes"] == 2
    assert q["locator_from"]["locator_question"] == "object"
    assert m["grasp_input"] is True and m["release_input"] is True
    assert [i["name"] for i in m["graphs"]["obs_encoder"]["inputs"]][-2:] == ["release_point", "grasp_point"]
    assert m["graphs"]["object_locator"]["file"] == "object_locator.onnx" and "object_locator.onnx" in m["files"]
    p = m["parity"]
    assert p["grasp_cond_max_abs_err"] <= STEP_TOL and p["object_locator_max_abs_err"] <= STEP_TOL
    with pytest.raises(ValueError, match="asks an object query"):  # again without it: refused, not dropped
        export(object_bundle / "bundle", object_bundle / "again", cache_dir=CACHE)
    with pytest.raises(ValueError, match="a later grasp of a long task"):
        export(object_bundle / "plain", object_bundle / "x", cache_dir=CACHE,
               object_query={"families": ["pick_place"], "data": object_bundle / "data",
                             "locator": object_bundle / "locator"})


def test_a_new_denoiser_keeps_a_bundles_queries_and_their_locators(object_bundle):
    from policy.bundle import Bundle

    root = object_bundle
    src = json.loads((root / "bundle" / "manifest.json").read_text())
    # the run again (as a fine-tuned denoiser would be), its locator rebuilt from the bundle's graph: the
    # locator's data and run need not exist any more
    # ... its release point moved towards the robot and kept for drawer_stow's later cycles (policy.object_query:
    # release_shift_m, keep_release)
    m = export(root / "run", root / "kept", cache_dir=CACHE, queries_from=root / "bundle",
               object_release_shift=(0.0, -0.03, 0.0), object_keep_release=["drawer_stow"])
    kept = dict(m["object_query"])
    record = kept.pop("kept_from")
    assert kept == {**src["object_query"], "release_shift_m": [0.0, -0.03, 0.0], "keep_release": ["drawer_stow"]}
    assert record["bundle"] == str(root / "bundle")
    spec = Bundle.load(root / "kept").object_query
    assert spec.release_shift == (0.0, -0.03, 0.0) and spec.keep_release == ("drawer_stow",)
    with pytest.raises(ValueError, match="no object query"):
        export(root / "run", root / "x", cache_dir=CACHE, object_release_shift=(0.0, -0.03, 0.0))
    with pytest.raises(ValueError, match="no object query"):
        export(root / "run", root / "x", cache_dir=CACHE, object_keep_release=["drawer_stow"])
    with pytest.raises(ValueError, match=r"--object-keep-release \['pick_place'\]: .*drawer_put, drawer_stow"):
        export(root / "run", root / "x", cache_dir=CACHE, queries_from=root / "bundle",
               object_keep_release=["pick_place"])
    assert record["locator_question"] == "object" and record["rebuilt_max_abs_err"] <= 1e-6
    assert m["grasp_input"] is True and m["files"]["object_locator.onnx"] == src["files"]["object_locator.onnx"]
    with pytest.raises(ValueError, match="asks no goal query or turn query to keep"):  # the object query anew
        export(root / "run", root / "x", cache_dir=CACHE, queries_from=root / "bundle",
               object_query={"families": ["drawer_put"], "data": root / "data", "locator": root / "locator"})
    with pytest.raises(ValueError, match="asks no goal query or object query"):
        export(root / "run", root / "x", cache_dir=CACHE, queries_from=root / "plain")


def test_a_given_grasp_point_moves_the_chunk_and_flag_0_is_the_heads(object_bundle):
    from policy.bundle import Bundle
    from policy.testing import random_observation

    plain, b = Bundle.load(object_bundle / "plain"), Bundle.load(object_bundle / "bundle")
    images, proprio = random_observation(b, 4)
    emb = b.embed(COMMAND)
    noise = np.random.default_rng(5).normal(size=(b.pred_horizon, b.action_dim)).astype(np.float32)
    a = plain.act(images, proprio, emb, noise=noise)
    np.testing.assert_allclose(b.act(images, proprio, emb, noise=noise, grasp=[0.3, 0.4, 0.1, 0.0]), a, atol=1e-5)
    moved = b.act(images, proprio, emb, noise=noise, grasp=[0.3, 0.4, 0.1, 1.0])
    assert np.abs(moved - a).max() > 1e-4
    with pytest.raises(ValueError, match="takes no grasp point"):
        plain.act(images, proprio, emb, grasp=[0.3, 0.4, 0.1, 1.0])
    with pytest.raises(ValueError, match="grasp: expected finite"):
        b.act(images, proprio, emb, grasp=[0.3, np.inf, 0.1, 1.0])
    # the locator graph's answer is the torch locator's (rounded to the graph's fp16 weights)
    from policy.oracle_eval import LocatedPoints

    loc, _, _ = load_run_model(object_bundle / "locator")
    asked = LocatedPoints(loc, emb, plain_normalizer(object_bundle), ticks=1)
    asked.ask(images, proprio)
    np.testing.assert_allclose(b.object_points(images, proprio, emb), asked.points, atol=2e-3)


def plain_normalizer(root):
    from policy.normalize import Normalizer

    return Normalizer.load(root / "locator" / "stats.npz")


class _Asked:
    """A bundle stand-in for ObjectQuery: counts the locator's questions, answers a fixed point per question."""

    object_query = None

    def __init__(self, spec):
        self.object_query, self.asked = spec, 0

    def embed(self, text):
        return np.zeros(768, np.float32)

    def object_points(self, images, proprio, emb):
        self.asked += 1
        return np.array([[0.1 * self.asked, 0.5, 0.05], [0.0, 0.6, 0.2]], np.float32)


def test_the_object_query_asks_at_the_start_and_gives_its_points_in_its_cycle_only():
    from policy.object_query import ObjectQuery, ObjectQuerySpec

    b = _Asked(ObjectQuerySpec(("drawer_put",), stage=1, ticks=3))
    q = ObjectQuery(b, COMMAND, "drawer_put")
    assert [q.inputs({}, None, 0) for _ in range(2)] == [{}, {}]  # opening the drawer: the head's own
    given = q.inputs({}, None, 1)
    assert b.asked == 3 and [q.inputs({}, None, 1) for _ in range(5)] and b.asked == 3  # asked three times only
    np.testing.assert_allclose(given["grasp"], [0.2, 0.5, 0.05, 1.0], atol=1e-6)  # the median, flagged
    np.testing.assert_allclose(given["release"], [0.0, 0.6, 0.2, 1.0], atol=1e-6)
    assert q.inputs({}, None, 2) == {}  # shutting it: the head's again
    for family, enabled in (("pick_place", True), ("drawer_put", False)):
        off = ObjectQuery(b, COMMAND, family, enabled=enabled)
        assert not off.active and off.inputs({}, None, 1) == {}
    assert not ObjectQuery(_Asked(None), COMMAND, "drawer_put").active


def test_a_manifest_object_query_is_checked_field_by_field():
    from policy.object_query import object_query_spec

    m = {"tasks": ["drawer_put"], "grasp_input": True,
         "object_query": {"families": ["drawer_put"], "stage": 1, "ticks": 3}}
    assert object_query_spec(m).families == ("drawer_put",) and object_query_spec({}) is None
    for change, match in (({"grasp_input": False}, "needs grasp_input"),
                          ({"object_query": {**m["object_query"], "families": ["stack"]}}, "families"),
                          ({"object_query": {**m["object_query"], "stage": 0}}, "stage"),
                          ({"object_query": {**m["object_query"], "ticks": 99}}, "ticks")):
        with pytest.raises(ValueError, match=match):
            object_query_spec({**m, **change})


def test_a_skill_phase_family_is_served_the_same_query_in_its_first_cycle():
    from policy.object_query import ObjectQuery, object_query_spec, with_skill_families

    table = {"families": ["drawer_put"], "stage": 1, "ticks": 3}
    assert with_skill_families(table, ["drawer_put", "stack"]) == table  # a bundle not taught drawer_stow
    grown = with_skill_families(table, ["drawer_put", "drawer_stow"])
    assert grown == {**table, "families": ["drawer_put", "drawer_stow"], "family_stage": {"drawer_stow": 0}}
    m = {"tasks": ["drawer_put", "drawer_stow"], "grasp_input": True, "object_query": grown}
    spec = object_query_spec(m)
    assert spec.stage_of("drawer_put") == 1 and spec.stage_of("drawer_stow") == 0
    b = _Asked(spec)
    stow = ObjectQuery(b, "put the red block in the open drawer", "drawer_stow")
    assert stow.inputs({}, None, 0)["grasp"][3] == 1.0 and stow.inputs({}, None, 1) == {}  # its object comes first
    for wrong in ({"drawer_stow": -1}, {"stack": 0}, {"drawer_stow": True}, ["drawer_stow"]):
        with pytest.raises(ValueError, match="family_stage"):
            object_query_spec({**m, "object_query": {**grown, "family_stage": wrong}})


def test_an_episode_asks_the_bundles_object_query(object_bundle):
    from policy.bundle import Bundle
    from runtime.evaluate import run_policy_episode

    b = Bundle.load(object_bundle / "bundle")
    out = run_policy_episode(b, "drawer_put", 3, dr="heavy", latency_s=0.006, time_limit_factor=0.02)
    assert np.asarray(out.object_points).shape == (2, 3)  # the object and where it goes, found at the start
    off = run_policy_episode(b, "drawer_put", 3, dr="heavy", latency_s=0.006, time_limit_factor=0.02,
                             goal_query=False)
    assert off.object_points is None
