"""The goal query (policy/goal_query.py): the role swap, the manifest table, the obs encoder's release input in
export, parity and the loader, a bundle exported again, and the query through `run_policy_episode`."""

import json
import shutil

import numpy as np
import pytest
import torch

from policy.bundle import Bundle, BundleError
from policy.bundle_import import model_from_bundle
from policy.config import AUX_TCP_SCALE
from policy.export import export
from policy.goal_query import GoalQuery, goal_query_spec, role_swap
from policy.graph_frames import with_release
from policy.model import prepare_images
from policy.parity import STEP_TOL
from policy.stage import with_stage
from policy.testing import STACK, StillBundle, goal_query_run, linked_copy, random_observation, synthetic_dataset
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()


@pytest.mark.parametrize("text, want", [
    (STACK, "stack the blue block on the red block"),
    ("put the red block on top of the blue block", "put the blue block on top of the red block"),
    ("place the small red block onto the big blue block", "place the big blue block onto the small red block"),
    ("set the red block down on the blue block", "set the blue block down on the red block"),
    ("could you put the red block onto the blue block", "could you put the blue block onto the red block"),
    ("put the red cube in the blue bin", None),  # a bin is no object to grasp: the goal's noun is not the object's
    ("open the drawer", None),
    ("stack the red block on it", None),
])
def test_role_swap_exchanges_the_two_object_phrases(text, want):
    assert role_swap(text) == want
    if want is not None:
        assert role_swap(want) == text


def _manifest(**q):
    return {"tasks": ["pick_place", "stack"], "release_input": True,
            "goal_query": {"families": ["stack"], "offset_m": [0.0, 0.0, 0.06], "ticks": 3, **q}}


@pytest.mark.parametrize("change, field", [
    ({"families": ["juggle"]}, "goal_query.families"), ({"families": []}, "goal_query.families"),
    ({"offset_m": [0.0, 0.0]}, "goal_query.offset_m"), ({"offset_m": [0.0, 0.0, 5.0]}, "goal_query.offset_m"),
    ({"offset_m": [0.0, float("nan"), 0.0]}, "goal_query.offset_m"), ({"ticks": 0}, "goal_query.ticks"),
    ({"ticks": 2.5}, "goal_query.ticks"),
])
def test_a_bad_goal_query_table_is_refused_naming_its_field(change, field):
    assert goal_query_spec(_manifest()).families == ("stack",)
    with pytest.raises(ValueError, match=field):
        goal_query_spec(_manifest(**change))
    with pytest.raises(ValueError, match="release_input"):
        goal_query_spec({**_manifest(), "release_input": False})
    assert goal_query_spec({"tasks": ["stack"]}) is None


@pytest.fixture(scope="module")
def exported(tmp_path_factory, loose_offsets):
    root = tmp_path_factory.mktemp("goal_query")
    data, _ = goal_query_run(root)
    export(root / "run", root / "plain", cache_dir=CACHE, pace={"stack": 0.5})
    export(root / "plain", root / "query", cache_dir=CACHE,
           goal_query={"families": ["stack"], "data": data, "ticks": 2})
    return root


def test_the_export_records_the_query_and_its_graph_takes_a_release_point(exported):
    m = json.loads((exported / "query" / "manifest.json").read_text())
    q = m["goal_query"]
    assert q["families"] == ["stack"] and q["ticks"] == 2 and len(q["offset_m"]) == 3
    assert q["measured"]["episodes"] > 0 and q["measured"]["release_cm_median"] >= 0
    assert m["release_input"] is True and m["dims"]["aux"] == 6
    assert [i["name"] for i in m["graphs"]["obs_encoder"]["inputs"]][-1] == "release_point"
    assert m["parity"]["release_cond_max_abs_err"] <= STEP_TOL and m["parity"]["aux_points_max_abs_err"] <= STEP_TOL
    # exported again from a bundle: its records are kept
    assert m["pace"] == {"stack": 0.5} and m["training"]["reexported_from"]["bundle"].endswith("plain")
    plain = json.loads((exported / "plain" / "manifest.json").read_text())
    assert "goal_query" not in plain and plain["release_input"] is False
    assert m["data"]["content_hash"] == plain["data"]["content_hash"]


def test_without_a_release_point_the_graph_acts_as_the_bundle_it_was_exported_from(exported):
    plain, query = Bundle.load(exported / "plain"), Bundle.load(exported / "query")
    images, proprio = random_observation(plain)
    emb = plain.embed(STACK)
    noise = np.random.default_rng(3).normal(size=(plain.pred_horizon, plain.action_dim)).astype(np.float32)
    a = plain.act(images, proprio, emb, noise=noise)
    np.testing.assert_allclose(query.act(images, proprio, emb, noise=noise), a, atol=1e-5)
    np.testing.assert_allclose(query.act(images, proprio, emb, noise=noise, release=[0.3, 0.4, 0.2, 0.0]), a, atol=1e-5)
    moved = query.act(images, proprio, emb, noise=noise, release=[0.3, 0.4, 0.2, 1.0])
    assert np.abs(moved - a).max() > 1e-4  # the denoiser reads the given point
    with pytest.raises(ValueError, match="takes no release point"):
        plain.act(images, proprio, emb, release=[0.3, 0.4, 0.2, 1.0])
    with pytest.raises(ValueError, match="release"):
        query.act(images, proprio, emb, release=[0.3, np.nan, 0.2, 1.0])


def test_the_grasp_point_is_the_heads_in_the_base_frame(exported):
    b = Bundle.load(exported / "query")
    model, normalizer, _ = model_from_bundle(exported / "query")  # the probe traces the release input alike
    images, proprio = random_observation(b, 1)
    emb = b.embed(STACK)
    cfg = model.cfg
    with torch.no_grad():
        imgs = {c: prepare_images(torch.from_numpy(images[c])[None], cfg.crop_size) for c in cfg.cameras}
        p = torch.from_numpy(with_stage(normalizer.normalize_proprio(proprio), 0, cfg.stage_bins))[None]
        head = model.aux_points(model.obs_encoder(imgs, p, torch.from_numpy(emb)[None]))[0, :3].numpy()
    from policy.action_frame import rotations

    pose = proprio[-1, :9].astype(np.float64)
    want = pose[:3] + rotations(pose[3:9]) @ (head * AUX_TCP_SCALE)
    np.testing.assert_allclose(b.grasp_point(images, proprio, emb), want, atol=1e-4)
    with pytest.raises(BundleError, match="release_input"):
        Bundle.load(exported / "plain").grasp_point(images, proprio, emb)


def test_with_release_replaces_only_the_flagged_release_point():
    points = torch.arange(12, dtype=torch.float32).reshape(2, 6)
    release = torch.tensor([[0.25, 0.5, 0.75, 1.0], [9.0, 9.0, 9.0, 0.0]])
    out = with_release(points, release)
    assert out[0].tolist() == [0, 1, 2, 1, 2, 3] and out[1].tolist() == points[1].tolist()


class _Counting:
    """A bundle that counts the goal query's questions."""

    def __init__(self, bundle):
        self.b, self.asked = bundle, []
        self.goal_query = bundle.goal_query

    def embed(self, text):
        return self.b.embed(text)

    def goal_point(self, images, proprio, emb, stage=0):
        self.asked.append(emb)
        return np.array([0.1 * len(self.asked), 0.5, 0.0], np.float32)


def test_the_query_asks_the_first_ticks_then_holds_their_median(exported):
    b = _Counting(Bundle.load(exported / "query"))
    images, proprio = random_observation(b.b)
    q = GoalQuery(b, STACK, "stack")
    assert q.active and q.swapped == "stack the blue block on the red block"
    got = [q.release(images, proprio)]
    assert not q.settled  # one of two asked
    got += [q.release(images, proprio) for _ in range(4)]
    assert q.settled and len(b.asked) == 2  # ticks = 2, then held (the policy node says the point once here)
    np.testing.assert_array_equal(b.asked[0], b.b.embed(q.swapped))
    offset = np.asarray(b.goal_query.offset_m)
    np.testing.assert_allclose(got[0][:3], [0.1, 0.5, 0.0] + offset, atol=1e-6)
    np.testing.assert_allclose(got[-1][:3], [0.15, 0.5, 0.0] + offset, atol=1e-6)  # the median of two
    assert all(r[3] == 1.0 for r in got)
    for off in (GoalQuery(b, "put the red cube in the blue bin", "stack"), GoalQuery(b, STACK, "pick_place"),
                GoalQuery(b, STACK, "stack", enabled=False), GoalQuery(b, STACK, None)):
        assert not off.active and off.release(images, proprio) is None


def test_a_manifest_whose_graph_lacks_the_release_input_is_refused(exported, tmp_path):
    bad = linked_copy(exported / "plain", tmp_path / "bad")
    m = json.loads((bad / "manifest.json").read_text())
    m["goal_query"] = {"families": ["stack"], "offset_m": [0, 0, 0.05], "ticks": 3}
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="release_input"):
        Bundle.load(bad, warmup=False, verify_hashes=False)
    m["release_input"] = True  # claimed, but the graph has no such input
    m["dims"]["aux"] = 6
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="release_point"):
        Bundle.load(bad, warmup=False, verify_hashes=False)


def test_the_measure_refuses_data_without_two_object_commands_and_a_head_far_off(exported, tmp_path, monkeypatch):
    data = synthetic_dataset(tmp_path / "data", episodes=6, tasks=("stack",), smooth=True)  # "do stack"
    with pytest.raises(ValueError, match="names two objects"):
        export(exported / "plain", tmp_path / "b", cache_dir=CACHE,
               goal_query={"families": ["stack"], "data": data, "ticks": 2})
    monkeypatch.setattr("policy.goal_query_measure.MAX_OFFSET_M", 0.3)  # the real limit, for this untrained head
    with pytest.raises(ValueError, match="longer than 0.3 m"):
        export(exported / "plain", tmp_path / "b", cache_dir=CACHE,
               goal_query={"families": ["stack"], "data": exported / "data", "ticks": 2})
    with pytest.raises(ValueError, match="--goal-query.juggle"):
        export(exported / "plain", tmp_path / "b", cache_dir=CACHE,
               goal_query={"families": ["juggle"], "data": exported / "data", "ticks": 2})
    with pytest.raises(ValueError, match="is a bundle"):
        export(exported / "plain", tmp_path / "b", cache_dir=CACHE, ema=False)
    assert not (tmp_path / "b").exists()
    shutil.rmtree(data)


def test_an_episode_asks_the_swapped_command_then_conditions_every_chunk_on_the_held_point():
    from runtime.evaluate import run_policy_episode

    still = StillBundle()
    out = run_policy_episode(still, "pick_place", 100_003, command=STACK, time_limit_factor=0.05, latency_s=0.006)
    assert len(still.asked) == 3 and len(still.releases) > 3
    np.testing.assert_array_equal(still.asked[0], still.embed("stack the blue block on the red block"))
    held = np.array([0.1, 0.42, 0.07])  # the median of the three answers plus the offset
    assert all(r is not None and r[3] == 1.0 for r in still.releases)
    np.testing.assert_allclose(still.releases[-1][:3], held, atol=1e-6)
    np.testing.assert_allclose(out.goal_point, held, atol=1e-4)
    off = StillBundle()
    out = run_policy_episode(off, "pick_place", 100_003, command=STACK, time_limit_factor=0.05, latency_s=0.006,
                             goal_query=False)
    assert not off.asked and all(r is None for r in off.releases) and out.goal_point is None
    other = StillBundle(families=("stack",))  # the family the episode is of is not listed
    run_policy_episode(other, "pick_place", 100_003, command=STACK, time_limit_factor=0.05, latency_s=0.006)
    assert not other.asked and all(r is None for r in other.releases)


def test_the_goal_query_switch_reaches_the_policy_node_of_every_stack(tmp_path):
    from runtime.launch import hardware_stack, policy_stack, sim_stack
    from runtime.nodes.common import config_from_dict, config_to_dict
    from runtime.nodes.policy_node import PolicyNodeConfig

    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["scene"], "image_size": [96, 96],
                                                        "horizons": {"action": 8}, "tasks": ["stack"]}))
    node = lambda spec: config_from_dict(PolicyNodeConfig, config_to_dict(spec.config))  # noqa: E731
    assert node(sim_stack(str(tmp_path))[1]).goal_query is True
    assert node(sim_stack(str(tmp_path), goal_query=False)[1]).goal_query is False
    assert node(policy_stack(str(tmp_path), goal_query=False)[0]).goal_query is False
    hw = hardware_stack(str(tmp_path), "10.0.0.2", {"scene": "123"}, goal_query=False)
    assert node(hw[-1]).goal_query is False
