"""A torch policy rebuilt from a bundle's ONNX graphs (policy.bundle_import), and a run warm-started from one."""

import json
import shutil
from pathlib import Path

import pytest
import torch

from policy.bundle_import import model_from_bundle
from policy.export import export
from policy.fp16 import round_weights_
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import load_run_model, train
from runtime.bench_runtime import test_cache_dir as cache_dir

ROOT = Path(__file__).resolve().parents[1]
CACHE = cache_dir()
# the shipped bundle's kind of model: aux head fed to the denoiser, release point in the base frame (the
# proprio normalization inside the graph), flow matching, gripper-frame actions
SHIPPED_LIKE = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "aux_condition": True,
                "aux_release_frame": "base", "objective": "flow", "obs_horizon": 1}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("import")
    data = synthetic_dataset(root / "data", episodes=4, tasks=("pick_place", "stack"), smooth=True)
    train(data, dict(TINY), root / "run", steps=4, embedder=hash_embedder, progress=False, threads=1,
          overrides=SHIPPED_LIKE)
    export(root / "run", root / "bundle", cache_dir=CACHE)
    return root


def test_rebuilt_weights_are_the_exported_ones(exported):
    model, normalizer, manifest = model_from_bundle(exported / "bundle")
    ref, _, _ = load_run_model(exported / "run")
    round_weights_(ref)  # the bundle stores the EMA weights rounded to fp16
    mine, theirs = model.state_dict(), ref.state_dict()
    assert set(mine) == set(theirs)
    for name in theirs:
        torch.testing.assert_close(mine[name], theirs[name], rtol=0, atol=0, msg=name)
    assert manifest["imported"]["not_in_graphs"] == []
    assert manifest["imported"]["parity"]["step_max_abs_err"] <= 1e-4
    assert (normalizer.proprio_scale == ref.proprio_scale.numpy()).all()


def test_a_bundle_from_another_export_is_refused_with_the_reason(exported, tmp_path):
    """Graphs that do not match what this code exports for the manifest's config (here: a config edited to
    another denoiser kernel) are refused, never read into the wrong parameters."""
    bad = tmp_path / "bundle"
    shutil.copytree(exported / "bundle", bad)
    manifest = json.loads((bad / "manifest.json").read_text())
    manifest["config"]["kernel_size"] += 2
    (bad / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="nodes differ|reads no"):
        model_from_bundle(bad)


def test_a_bundle_exported_again_keeps_its_phased_families_unless_given(exported, tmp_path):
    """The manifest's `phased` (policy/phased.py) is a measured record like the pace: kept on re-export,
    replaced by what is given (none: [])."""
    from policy.bundle import Bundle
    from policy.testing import linked_copy

    src = linked_copy(exported / "bundle", tmp_path / "src")
    m = json.loads((src / "manifest.json").read_text())
    (src / "manifest.json").write_text(json.dumps({**m, "tasks": [*m["tasks"], "drawer_put"],
                                                   "phased": ["drawer_put"]}))
    kept = export(src, tmp_path / "kept", cache_dir=CACHE)
    assert kept["phased"] == ["drawer_put"] and Bundle.load(tmp_path / "kept", warmup=False).phased == ("drawer_put",)
    dropped = export(src, tmp_path / "dropped", cache_dir=CACHE, phased=[])
    assert "phased" not in dropped and Bundle.load(tmp_path / "dropped", warmup=False).phased == ()


def test_a_run_warm_started_from_a_bundle_starts_from_its_weights(exported):
    run = exported / "from_bundle"
    # the bundle as the config too: the one it was trained with (its manifest's)
    train(exported / "data", exported / "bundle", run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          overrides={"lr": 0.0, "warmup_steps": 0}, init_from=exported / "bundle")
    record = json.loads((run / "warm_start.json").read_text())
    assert record["bundle"] is True and record["grown"] == [] and record["new"] == []
    after, _, _ = load_run_model(run)
    src, _, _ = model_from_bundle(exported / "bundle")
    for name, value in src.state_dict().items():  # lr 0: the weights the run starts from, unchanged
        torch.testing.assert_close(after.state_dict()[name], value, msg=name)


def test_a_fine_tune_on_some_families_still_lists_what_its_warm_start_learned(exported):
    """Fine-tuned on one family's episodes, the weights still know the bundle's other families and commands:
    the export lists them all (the policy node accepts only listed commands), and says how many came along."""
    data = synthetic_dataset(exported / "data_do", episodes=2, tasks=("drawer_open",),
                             instructions={"drawer_open": "open the cupboard"})
    run, out = exported / "ft_do", exported / "bundle_ft"
    train(data, exported / "bundle", run, steps=2, embedder=hash_embedder, progress=False, threads=1,
          init_from=exported / "bundle")
    chained = exported / "ft_do2"  # a run from that run: the chain's instructions carry on
    train(data, exported / "bundle", chained, steps=1, embedder=hash_embedder, progress=False, threads=1,
          init_from=run)
    source = json.loads((exported / "bundle/manifest.json").read_text())
    export(chained, out, cache_dir=CACHE)
    manifest = json.loads((out / "manifest.json").read_text())
    assert "drawer_open" not in source["tasks"] and source["instructions"]
    assert manifest["tasks"] == sorted({*source["tasks"], "drawer_open"})
    assert manifest["instructions"] == sorted({*source["instructions"], "open the cupboard"})
    assert manifest["training"]["warm_start"]["learned_instructions"] == len(source["instructions"]) + 1
    assert "learned" not in manifest["training"]["warm_start"]


SHIPPED = sorted(p.parent.name for p in (ROOT / "policy/bundles").glob("*/manifest.json"))


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_bundle_rebuilds_in_torch_and_says_how_it_was_made(name):
    bundle = ROOT / "policy/bundles" / name
    recipe = (bundle / "RECIPE.md").read_text()
    assert "sudd train" in recipe and "sudd export" in recipe and "sudd eval" in recipe
    if not (bundle / "text_encoder.onnx").is_file():
        pytest.skip("the text encoder is restored by `make` (sudd export --restore-text-encoder)")
    model, _, manifest = model_from_bundle(bundle)
    imported = manifest["imported"]
    assert imported["not_in_graphs"] == []
    assert imported["parameters"] == manifest["params"]["policy_total"]
    assert imported["parity"]["step_max_abs_err"] <= 1e-4 and imported["parity"]["chunk_max_abs_err"] <= 1e-3
    for task in manifest["tasks"]:  # every family it was trained on is in its recipe's results
        assert f"| {task} |" in recipe


def test_pretraining_from_a_bundle_starts_from_its_encoders_and_keeps_its_stats(exported, tmp_path):
    """`sudd pretrain --init-from BUNDLE`: more families' views for a shipped policy's encoders, which were
    trained with the bundle's normalization, so the run keeps that rather than fitting the data's."""
    import numpy as np

    from datagen.views import generate
    from policy.config import load_policy_config
    from policy.data import PolicyDataset
    from policy.pretrain import pretrain

    views = tmp_path / "views"
    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    generate(views, range(300, 301), 2, offsets, progress=False, image_size=tuple(TINY["image_size"]))
    other = synthetic_dataset(tmp_path / "other", episodes=9, smooth=True)  # not the data the bundle saw
    s = pretrain(views, other, exported / "bundle", tmp_path / "pre", 2, {"lr": 0.0, "warmup_steps": 0},
                 threads=1, progress=False, embedder=hash_embedder, init_from=exported / "bundle")
    src, normalizer, _ = model_from_bundle(exported / "bundle")
    after = torch.load(s["checkpoint"], weights_only=False)["ema"]["model"]
    for name, value in src.state_dict().items():
        if name.startswith(("obs_encoder.images.", "aux_head.")):
            torch.testing.assert_close(after[name], value, msg=name)
    kept = np.load(tmp_path / "pre" / "stats.npz")
    np.testing.assert_array_equal(kept["proprio_scale"], normalizer.proprio_scale)
    fitted = PolicyDataset(other, load_policy_config(exported / "bundle"), train=False, embedder=hash_embedder)
    assert not np.array_equal(fitted.normalizer.proprio_scale, normalizer.proprio_scale)  # what a fit would give
    assert json.loads((tmp_path / "pre" / "warm_start.json").read_text())["bundle"] is True


def test_a_bundle_is_validated_on_another_datasets_held_out_episodes_family_by_family(exported, tmp_path, capsys):
    import numpy as np

    from policy.validate import validate_model
    from runtime.cli import main

    data = synthetic_dataset(tmp_path / "five", episodes=10, tasks=("pick_place", "stack"), smooth=True)
    got = validate_model(exported / "bundle", data, samples=64, val_fraction=0.5, embedder=hash_embedder)
    assert {"val_chunk_cm.pick_place", "val_chunk_cm.stack", "val_pregrasp_cm.pick_place"} <= set(got)
    assert all(np.isfinite(v) for v in got.values())
    # the run it was exported from gives the same figures (fp16 weights: to a few hundredths of a cm)
    run = validate_model(exported / "run", data, samples=64, val_fraction=0.5, embedder=hash_embedder)
    assert run["val_pregrasp_cm"] == pytest.approx(got["val_pregrasp_cm"], abs=0.05)
    assert main(["validate", str(exported / "bundle"), "--data", str(data)]) == 2  # trained on every episode
    assert "no episodes of its own are held out; give a val_fraction" in capsys.readouterr().err
