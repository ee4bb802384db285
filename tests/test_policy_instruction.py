"""The instruction as the policy reads it (policy.instruction, config text_goal): the goal clause of every task
family's commands, the [sentence, goal clause] vector, its bundle, and a warm start onto it."""

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from policy.bundle import Bundle, BundleError
from policy.config import TEXT_DIM, load_policy_config
from policy.export import export
from policy.instruction import embed_instructions, goal_clause
from policy.model import DiffusionPolicy
from policy.normalize import Normalizer
from policy.testing import TINY, hash_embedder, linked_copy, synthetic_dataset
from policy.train import train
from policy import warm_start
from runtime.bench_runtime import test_cache_dir as cache_dir
from sim.dr_config import DRConfig
from sim.tasks.registry import get_task


@pytest.mark.parametrize("family, goal_field", [("pick_place", "bin"), ("stack", "bottom"), ("drawer_put", None),
                                                ("drawer_open", None), ("drawer_close", None)])
def test_the_goal_clause_names_the_goal_and_not_the_object(family, goal_field):
    task = get_task(family)
    for seed in range(12):
        inst = task.sample(np.random.default_rng(seed), DRConfig())
        fields = task.fields(inst)
        for text in (inst.instruction, task.paraphrase(inst, np.random.default_rng(seed))):
            clause = goal_clause(text)
            if family.startswith("drawer_") and family != "drawer_put":
                assert clause is None, text
                continue
            assert clause is not None and text.endswith(clause), text
            moved = fields.get("obj") or fields.get("top")
            assert moved not in clause, (text, clause)
            if goal_field:
                assert fields[goal_field] in clause, (text, clause)
            else:
                assert "drawer" in clause, (text, clause)


def test_no_goal_clause_in_a_preposition_that_opens_or_ends_a_sentence():
    assert goal_clause("on the table") is None and goal_clause("put it in") is None
    assert goal_clause("put the red block on top of the blue block") == "on top of the blue block"


def test_the_vector_is_the_sentence_then_its_goal_clause_or_zeros():
    texts = ["stack the red block on the blue block", "open the drawer"]
    plain = embed_instructions(hash_embedder, texts, goal=False)
    np.testing.assert_array_equal(plain, hash_embedder(texts))
    both = embed_instructions(hash_embedder, texts, goal=True)
    assert both.shape == (2, 2 * TEXT_DIM) and both.dtype == np.float32
    np.testing.assert_array_equal(both[:, :TEXT_DIM], plain)
    np.testing.assert_array_equal(both[0, TEXT_DIM:], hash_embedder(["on the blue block"])[0])
    assert not both[1, TEXT_DIM:].any()


def test_minilm_tells_swapped_roles_apart_only_in_the_goal_slot():
    from policy.text import default_embedder

    a, b = embed_instructions(default_embedder(), ["stack the red block on the blue block",
                                                   "stack the blue block on the red block"], goal=True)
    cos = lambda u, v: float(u @ v / np.linalg.norm(u) / np.linalg.norm(v))  # noqa: E731
    assert cos(a[:TEXT_DIM], b[:TEXT_DIM]) > 0.99  # why the goal slot exists
    assert cos(a[TEXT_DIM:], b[TEXT_DIM:]) < 0.9


@pytest.fixture(scope="module")
def goal_runs(tmp_path_factory):
    """A TINY run on commands with goal clauses, and one with text_goal warm-started from it."""
    root = tmp_path_factory.mktemp("goal")
    data = synthetic_dataset(root / "data", episodes=4, tasks=("pick_place", "stack"), smooth=True,
                             instructions={"pick_place": "put the red block in the green bin",
                                           "stack": "stack the red block on the blue block"})
    plain = dict(TINY, val_fraction=0.0)
    train(data, plain, root / "plain", steps=4, embedder=hash_embedder, progress=False, threads=1)
    train(data, dict(plain, text_goal=True), root / "goal", steps=4, embedder=hash_embedder, progress=False,
          threads=1, init_from=root / "plain")
    return root


def test_a_warm_start_onto_the_goal_slot_computes_what_its_source_did(goal_runs):
    cfg = load_policy_config(dict(TINY, val_fraction=0.0))
    source = DiffusionPolicy(cfg)
    source.load_state_dict(torch.load(warm_start.source_checkpoint(goal_runs / "plain"),
                                      weights_only=False)["ema"]["model"])
    grown = DiffusionPolicy(load_policy_config(dict(TINY, val_fraction=0.0, text_goal=True)))
    record = warm_start.load_into(grown, goal_runs / "plain")
    assert any("text" in g for g in record["grown"])
    g = torch.Generator().manual_seed(1)
    imgs = {c: torch.rand(1, cfg.obs_horizon, 3, *cfg.crop_size, generator=g) for c in cfg.cameras}
    proprio, text = torch.randn(1, cfg.obs_horizon, cfg.proprio_dim, generator=g), torch.randn(1, TEXT_DIM, generator=g)
    with torch.no_grad():
        want = source.encode(imgs, proprio, text)
        got = grown.encode(imgs, proprio, torch.cat([text, torch.randn(1, TEXT_DIM, generator=g)], dim=1))
    torch.testing.assert_close(got, want)


def test_a_goal_bundle_embeds_both_slots_and_refuses_a_wrong_width(goal_runs, tmp_path):
    export(goal_runs / "goal", tmp_path / "bundle", cache_dir=cache_dir())
    manifest = json.loads((tmp_path / "bundle" / "manifest.json").read_text())
    assert manifest["instruction"] == {"goal_clause": True} and manifest["dims"]["instruction"] == 2 * TEXT_DIM
    b = Bundle.load(tmp_path / "bundle")
    e = b.embed("put the red block in the green bin")
    assert e.shape == (2 * TEXT_DIM,) and np.linalg.norm(e[TEXT_DIM:]) == pytest.approx(1.0, abs=1e-4)
    assert not b.embed("open the drawer")[TEXT_DIM:].any()
    best, cos = b.task_similarity("put the red block in the green bin")
    assert best == "put the red block in the green bin" and cos == pytest.approx(1.0, abs=1e-5)
    imgs = {c: np.zeros((b.obs_horizon, *b.image_size, 3), np.uint8) for c in b.cameras}
    proprio = np.zeros((b.obs_horizon, b.proprio_dim), np.float32)
    assert np.isfinite(b.act(imgs, proprio, e, rng=np.random.default_rng(0))).all()
    with pytest.raises(ValueError, match=r"expected finite \(768,\)"):
        b.act(imgs, proprio, e[:TEXT_DIM])
    broken = linked_copy(tmp_path / "bundle", tmp_path / "broken")
    m = json.loads((broken / "manifest.json").read_text())
    m["instruction"]["goal_clause"] = False
    (broken / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="dims.instruction 768 does not match"):
        Bundle.load(broken, warmup=False)


def test_encoders_from_takes_a_pretrain_runs_encoders_and_keeps_the_denoiser(goal_runs, tmp_path):
    cfg = load_policy_config(dict(TINY, val_fraction=0.0, text_goal=True))
    pre = tmp_path / "pre"
    shutil.copytree(goal_runs / "goal", pre)
    with pytest.raises(ValueError, match="not a `sudd pretrain` run"):
        warm_start.load_pretrained_into(DiffusionPolicy(cfg), pre, Normalizer.load(pre / "stats.npz"))
    (pre / "dataset.json").write_text(json.dumps({"pretrain": "views"}))
    theirs = torch.load(warm_start.source_checkpoint(pre), weights_only=False)["ema"]["model"]
    model = DiffusionPolicy(cfg)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    warm_start.load_pretrained_into(model, pre, Normalizer.load(pre / "stats.npz"))
    for k, v in model.state_dict().items():
        want = theirs[k] if k.startswith(tuple(p + "." for p in warm_start.PRETRAINED)) else before[k]
        torch.testing.assert_close(v, want, msg=k)
    mine = Normalizer.load(pre / "stats.npz")
    other = dataclasses.replace(mine, proprio_scale=mine.proprio_scale * 2)
    with pytest.raises(ValueError, match="proprio_scale differs"):
        warm_start.load_pretrained_into(model, pre, other)
