"""Export and the runtime loader: torch/onnxruntime parity, fp16 weight storage and Bundle.load's refusals (the
text encoder's tests are in test_policy_text_encoder.py)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policy.bundle import Bundle, BundleError, expected_graphs
from policy.export import export
from policy.fp16 import round_weights_
from policy.normalize import Normalizer
from policy.parity import CHUNK_TOL, STEP_TOL
from policy.sampling import predict_chunk
from policy.testing import linked_copy, tiny_run
from policy.train import load_run_model
from runtime.bench_runtime import test_cache_dir as cache_dir
from sim.config import ConfigError

ROOT = Path(__file__).resolve().parents[1]
CACHE = cache_dir()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return tiny_run(tmp_path_factory.mktemp("policy"))


@pytest.fixture(scope="module")
def bundle_dir(run):
    export(run, run.parent / "bundle", cache_dir=CACHE)
    return run.parent / "bundle"


@pytest.fixture(scope="module")
def bundle(bundle_dir):
    return Bundle.load(bundle_dir)


def test_layout_and_manifest(run, bundle_dir):
    m = json.loads((bundle_dir / "manifest.json").read_text())
    assert m["training"]["machine"] == json.loads((Path(run) / "environment.json").read_text())  # where it trained
    for name in ("manifest.json", "obs_encoder.onnx", "denoiser.onnx", "text_encoder.onnx", "stats.npz",
                 "tokenizer/tokenizer.json", "text_reference.npy"):
        assert (bundle_dir / name).is_file(), name
    assert m["format"] == "sudd-policy-bundle" and m["format_version"] == 1 and m["opset"] == 17
    assert m["horizons"] == {"obs": 2, "pred": 16, "action": 8, "execute_from": 1, "control_hz": 10.0}
    assert m["tasks"] == ["pick_place", "stack"] and m["instructions"] == ["do pick_place", "do stack"]
    assert len(m["data"]["content_hash"]) == 64 and m["training"]["ema"] is True
    assert len(m["ddim"]["timesteps"]) == m["config"]["inference_steps"] <= 8
    assert m["sampling"] == {"noise_scale": 1.0} and m["pace"] == {}  # every family at the recorded pace
    assert m["graphs"] == {k: dict(v, file=m["graphs"][k]["file"]) for k, v in expected_graphs(m).items()}
    assert m["parity"]["step_max_abs_err"] <= STEP_TOL and m["parity"]["chunk_max_abs_err"] <= CHUNK_TOL
    assert m["text_encoder"]["int8_min_cosine_vs_fp32"] >= 0.99
    te = m["text_encoder"]
    assert te["restorable"] and "text_encoder.onnx" in te["files"] and "tokenizer/tokenizer.json" in te["files"]
    assert np.load(bundle_dir / te["reference"]["file"]).shape == (len(te["reference"]["sentences"]), 384)
    assert m["weights"]["dtype"] == "float16" and m["weights"]["denoiser"]["max_rel_change"] == 0.0
    assert 0 < m["weights"]["rounding"]["chunk_max_abs_diff_normalized"] < 0.05
    assert (bundle_dir / "text_encoder.onnx").stat().st_size < 30e6  # int8: ~23 MB instead of ~90 MB


def test_parity_torch_vs_onnxruntime(run, bundle):
    model, cfg, _ = load_run_model(run)
    round_weights_(model)  # the bundle stores fp16 weights: it reproduces the rounded model exactly
    norm = Normalizer.load(run / "stats.npz")
    rng = np.random.default_rng(42)
    step_err = chunk_err = 0.0
    for _ in range(3):
        images = {c: rng.integers(0, 256, (2, *cfg.image_size, 3), dtype=np.uint8) for c in cfg.cameras}
        proprio = norm.proprio_min + (norm.proprio_max - norm.proprio_min) * rng.random((2, 16), dtype=np.float32)
        text = bundle.embed("do stack")
        noise = rng.normal(size=(16, 10)).astype(np.float32)
        trace = []
        chunk = bundle.act(images, proprio, text, noise=noise, trace=trace)
        with torch.no_grad():
            for x, t, eps in trace[1:]:
                ref = model.unet.denoise(torch.from_numpy(x), torch.tensor([t]), torch.from_numpy(trace[0]))
                step_err = max(step_err, float(np.abs(ref.numpy() - eps).max()))
        ref_chunk = predict_chunk(model, norm, images, proprio, text, noise)
        chunk_err = max(chunk_err, float(np.abs(ref_chunk - chunk).max()))
    assert step_err <= 1e-4 and chunk_err <= 1e-3, (step_err, chunk_err)


def test_act_outputs(bundle):
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8) for c in bundle.cameras}
    proprio = np.tile(np.array([0.3, -0.2, 0.25, 1, 0, 0, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0], np.float32), (2, 1))
    e = bundle.embed("do pick_place")
    a = bundle.act(images, proprio, e, rng=np.random.default_rng(1))
    assert a.shape == (16, 10) and a.dtype == np.float32 and np.all(np.isfinite(a))
    x, y = a[:, 3:6], a[:, 6:9]
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose((x * y).sum(1), 0, atol=1e-5)
    lo, hi = bundle.stats["action_min"], bundle.stats["action_max"]
    for d in (0, 1, 2, 9):  # clipped DDIM: absolute targets stay inside the demonstrated range
        assert lo[d] - 1e-5 <= a[:, d].min() and a[:, d].max() <= hi[d] + 1e-5
    np.testing.assert_array_equal(a, bundle.act(images, proprio, e, rng=np.random.default_rng(1)))
    assert not np.array_equal(a, bundle.act(images, proprio, e, rng=np.random.default_rng(2)))
    assert a[bundle.execute].shape == (8, 10)
    bundle.noise_scale = 0.0  # the temperature scales only the drawn noise: 0 gives the zero-noise chunk
    try:
        np.testing.assert_array_equal(bundle.act(images, proprio, e, rng=np.random.default_rng(2)),
                                      bundle.act(images, proprio, e, noise=np.zeros((16, 10), np.float32)))
    finally:
        bundle.noise_scale = 1.0
    with pytest.raises(ValueError, match="image 'scene'"):
        bundle.act(dict(images, scene=images["scene"][:, :16]), proprio, e)
    with pytest.raises(ValueError, match="proprio"):
        bundle.act(images, proprio[:1], e)


def test_act_samples_are_a_batch_of_single_chunks(bundle):
    rng = np.random.default_rng(3)
    images = {c: rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8) for c in bundle.cameras}
    proprio = np.tile(np.array([0.3, -0.2, 0.25, 1, 0, 0, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0], np.float32), (2, 1))
    e = bundle.embed("do stack")
    noise = rng.normal(size=(3, 16, 10)).astype(np.float32)
    batch = bundle.act(images, proprio, e, noise=noise, samples=3)
    assert batch.shape == (3, 16, 10)
    for k in range(3):  # each sample is the chunk its noise gives alone
        np.testing.assert_allclose(batch[k], bundle.act(images, proprio, e, noise=noise[k]), atol=1e-5)
    # one sample draws what a single chunk draws: K = 1 is the plain sampler
    np.testing.assert_array_equal(bundle.act(images, proprio, e, rng=np.random.default_rng(5), samples=1)[0],
                                  bundle.act(images, proprio, e, rng=np.random.default_rng(5)))
    with pytest.raises(ValueError, match="samples = 0"):
        bundle.act(images, proprio, e, samples=0)


def test_task_similarity(bundle):
    best, cos = bundle.task_similarity("do stack")
    assert best == "do stack" and cos == pytest.approx(1.0, abs=1e-5)
    best, cos_far = bundle.task_similarity("tell me a joke about penguins")
    assert cos_far < 0.5


def _edit(path: Path, fn) -> None:
    m = json.loads((path / "manifest.json").read_text())
    fn(m)
    (path / "manifest.json").write_text(json.dumps(m))


def _rehash(path: Path, rel: str) -> None:
    import hashlib

    data = (path / rel).read_bytes()
    _edit(path, lambda m: m["files"].__setitem__(rel, {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}))


def _flip(data: bytes) -> bytes:
    k = len(data) // 2
    return data[:k] + bytes([data[k] ^ 1]) + data[k + 1:]


def _pred24(m):
    m["horizons"]["pred"] = 24
    for k, v in expected_graphs(m).items():
        m["graphs"][k].update(v)


def _bad_stats(p: Path):
    with np.load(p / "stats.npz") as z:
        d = dict(z)
    d["action_scale"] = d["action_scale"][:9]
    np.savez(p / "stats.npz", **d)
    _rehash(p, "stats.npz")


@pytest.mark.parametrize("breakage, reason", [
    (lambda p: (p / "denoiser.onnx").unlink(), "missing file denoiser.onnx"),
    (lambda p: (p / "manifest.json").unlink(), "missing file manifest.json"),
    (lambda p: _edit(p, lambda m: m.__setitem__("format_version", 2)), "format_version 2"),
    (lambda p: _edit(p, lambda m: m.__setitem__("format", "zip")), "not a policy bundle"),
    (lambda p: _edit(p, lambda m: m.__setitem__("opset", 99)), "opset 99 is outside"),
    (lambda p: _edit(p, lambda m: m.__setitem__("opset", 16)), "uses opset 17, the manifest declares 16"),
    (lambda p: _edit(p, lambda m: m["horizons"].__setitem__("pred", 24)), "do not follow"),
    (lambda p: _edit(p, _pred24), "denoiser.onnx inputs are"),
    (lambda p: _edit(p, lambda m: m["dims"].__setitem__("cond", 7)), "do not follow"),
    (_bad_stats, "action_scale has shape"),
    (lambda p: (p / "stats.npz").write_bytes(_flip((p / "stats.npz").read_bytes())), "content differs"),
    (lambda p: (p / "stats.npz").write_bytes(b"garbage"), "7 bytes, manifest says"),
    (lambda p: _edit(p, lambda m: m.pop("ddim")), "exactly one sampler schedule"),
    (lambda p: _edit(p, lambda m: m.__setitem__("sampling", {"noise_scale": 1.5})), "noise_scale 1.5 is outside"),
    (lambda p: _edit(p, lambda m: m.__setitem__("pace", {"stack": 0.0})), r"manifest pace.stack 0.0: expected"),
    (lambda p: _edit(p, lambda m: m.__setitem__("pace", {"drawer_open": 0.5})), "pace.drawer_open: unknown task"),
    (lambda p: _edit(p, lambda m: m.__setitem__("phased", ["stack"])), "manifest phased: 'stack' has no phases"),
    (lambda p: _edit(p, lambda m: m.__setitem__("phased", ["drawer_put"])), "'drawer_put' is not one of the bundle"),
])
def test_load_refuses_broken_bundles(bundle_dir, tmp_path, breakage, reason):
    broken = linked_copy(bundle_dir, tmp_path / "b")
    Bundle.load(broken, warmup=False)  # intact before the breakage
    breakage(broken)
    with pytest.raises(BundleError, match=reason):
        Bundle.load(broken, warmup=False)


def test_a_linked_copy_made_from_a_relative_path_loads(bundle_dir, tmp_path, monkeypatch):
    monkeypatch.chdir(Path(bundle_dir).parent)
    copy = linked_copy(Path(bundle_dir).name, tmp_path / "copy")
    assert Bundle.load(copy, warmup=False).cameras


def test_bundle_module_does_not_import_torch(bundle_dir):
    code = (f"import sys, numpy as np; from policy.bundle import Bundle; b = Bundle.load({str(bundle_dir)!r}); "
            "b.act({c: np.zeros((2, 32, 32, 3), np.uint8) for c in b.cameras}, np.zeros((2, 16)), b.embed('hi')); "
            "assert 'torch' not in sys.modules and 'transformers' not in sys.modules, 'torch imported'")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_fp16_weights_halve_the_policy_graphs(run, bundle_dir, tmp_path):
    m16 = export(run, tmp_path / "fp32", cache_dir=CACHE, fp16_weights=False)  # fp16 is bundle_dir's default
    m16, m32 = json.loads((bundle_dir / "manifest.json").read_text()), m16
    size = lambda m: sum(m["files"][f]["bytes"] for f in ("obs_encoder.onnx", "denoiser.onnx"))  # noqa: E731
    assert size(m16) < 0.7 * size(m32), (size(m16), size(m32))  # tiny graphs: the node list is a third of the bytes
    assert m32["weights"] == {"dtype": "float32", "obs_encoder": {"dtype": "float32"}, "denoiser": {"dtype": "float32"}}
    for m in (m16, m32):
        assert m["parity"]["step_max_abs_err"] <= STEP_TOL and m["parity"]["chunk_max_abs_err"] <= CHUNK_TOL


def test_cli_export(run, tmp_path, capsys, monkeypatch):
    import argparse

    from policy.cli import parse_overrides, register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["export", str(run), "--out", str(tmp_path / "b"), "--inference-steps", "3",
                              "--noise-scale", "0.5", "--pace", "stack=0.5"])
    monkeypatch.setenv("SUDD_CACHE_DIR", str(CACHE))
    assert args.func(args) == 0
    assert "parity step" in capsys.readouterr().out and (tmp_path / "b" / "manifest.json").is_file()
    m = json.loads((tmp_path / "b" / "manifest.json").read_text())  # the bundle samples with 3 steps, checked
    assert len(m["ddim"]["timesteps"]) == 3 and m["config"]["inference_steps"] == 3
    assert m["parity"]["chunk_max_abs_err"] <= CHUNK_TOL and len(Bundle.load(tmp_path / "b")._schedule) == 3
    assert m["sampling"] == {"noise_scale": 0.5} and Bundle.load(tmp_path / "b", warmup=False).noise_scale == 0.5
    assert m["pace"] == {"stack": 0.5} and Bundle.load(tmp_path / "b", warmup=False).pace.speed("stack") == 0.5
    with pytest.raises(ValueError, match=r"--pace.drawer_open: unknown task family; expected one of \['pick_place', "
                                         r"'stack'\]"):  # a family the run's data has not: before exporting
        args.func(parser.parse_args(["export", str(run), "--out", str(tmp_path / "c"), "--pace", "drawer_open=0.5"]))
    assert not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match=r"--phased: 'drawer_put' is not one of the bundle's task families"):
        args.func(parser.parse_args(["export", str(run), "--out", str(tmp_path / "c"), "--phased", "drawer_put"]))
    assert not (tmp_path / "c").exists() and "phased" not in m  # none unless given
    with pytest.raises(ConfigError, match="inference_steps"):
        args.func(parser.parse_args(["export", str(run), "--out", str(tmp_path / "c"), "--inference-steps", "0"]))
    with pytest.raises(ConfigError, match="noise_scale"):
        args.func(parser.parse_args(["export", str(run), "--out", str(tmp_path / "c"), "--noise-scale", "2"]))
    (tmp_path / "b" / "text_encoder.onnx").unlink()
    args = parser.parse_args(["export", "--restore-text-encoder", str(tmp_path / "b")])
    assert args.func(args) == 0 and "text encoder restored" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--restore-text-encoder BUNDLE"):
        args.func(parser.parse_args(["export", str(run)]))  # neither --out nor --restore-text-encoder
    targs = parser.parse_args(["train", "data", "--out", "r", "--steps", "5", "--set", "lr=0.001", "--set", "preset=full"])
    assert targs.steps == 5 and parse_overrides(targs.set) == {"lr": 0.001, "preset": "full"}
    with pytest.raises(SystemExit):
        parser.parse_args(["train", "data", "--out", "r"])  # --steps or --epochs is required


def test_cli_train_passes_its_thread_count_and_stop_step_and_refuses_zero(monkeypatch, capsys):
    import argparse

    import policy.train
    from policy.cli import register

    seen = []
    monkeypatch.setattr(policy.train, "train", lambda *a, **kw: seen.append((kw["threads"], kw["stop_at"])) or {
        "run_dir": "r", "step": 1, "total_steps": 1, "final_loss": 0.5, "checkpoint": None, "plot": None})
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    for extra in (["--threads", "1", "--stop-at", "3"], []):
        args = parser.parse_args(["train", "data", "--out", "r", "--steps", "5", *extra])
        assert args.func(args) == 0
    assert seen == [(1, 3), (None, None)]
    for bad, why in ((["--threads", "0"], "--threads 0: expected a positive number"),
                     (["--stop-at", "0"], "--stop-at 0: expected a step >= 1")):
        with pytest.raises(ValueError, match=why):
            args = parser.parse_args(["train", "data", "--out", "r", "--steps", "5", *bad])
            args.func(args)


class _StandIn:
    """The bundle interface policy.sensitivity uses; actions depend on what `uses` names."""

    obs_horizon, cameras, pred_horizon, action_dim, execute = 2, ("scene", "wrist"), 16, 10, slice(1, 9)

    def __init__(self, uses):
        self.uses = uses

    def embed(self, text):
        return np.full(384, float(len(text)), np.float32)

    def act(self, images, proprio, emb, noise=None, rng=None):
        a = np.asarray(noise, np.float32) * 0.01
        if "scene" in self.uses:
            a[:, :3] += images["scene"].mean() / 255.0
        if "proprio" in self.uses:
            a[:, :3] += proprio[-1, :3]
        return a


def test_input_sensitivity_finds_the_inputs_a_policy_ignores(run, bundle):
    from policy.sensitivity import blind_cameras, input_sensitivity

    data = run.parent / "data"
    blind = input_sensitivity(_StandIn({"proprio"}), data, samples=6)
    assert blind["image_scene"] == blind["image_wrist"] == blind["text"] == 0.0
    assert blind["proprio"] > 0 and blind["noise"] > 0 and blind["samples"] == 6
    assert blind_cameras(blind) == ["scene", "wrist"]
    seeing = input_sensitivity(_StandIn({"scene", "proprio"}), data, samples=6)
    assert seeing["image_scene"] > 0 and blind_cameras(seeing) == ["wrist"]
    real = input_sensitivity(bundle, data, samples=4)  # the ONNX bundle on recorded windows
    assert set(real) >= {"image_scene", "image_wrist", "proprio", "text", "noise"} and real["noise"] > 0


class _Follower(_StandIn):
    """A stand-in that goes `gain` of the way from the recorded proprio to a given release (or grasp) point."""

    obs_horizon, release_input, grasp_input = 1, True, True

    def __init__(self, gain, point="release"):
        super().__init__(set())
        self.gain, self.point = gain, point

    def act(self, images, proprio, emb, noise=None, rng=None, release=None, grasp=None):
        given = {"release": release, "grasp": grasp}
        a = np.zeros((self.pred_horizon, self.action_dim), np.float32)
        a[:, :3] = proprio[-1, :3]
        if given[self.point] is not None:  # the other point moves nothing
            a[:, :3] = (1 - self.gain) * proprio[-1, :3] + self.gain * np.asarray(given[self.point][:3])
        return a


@pytest.mark.parametrize("point", ["release", "grasp"])
def test_point_gain_says_how_far_the_chunk_follows_a_given_point(run, tmp_path, point):
    from datagen.store import ShardWriter
    from datagen.workers import synthetic_episode
    from policy.sensitivity import point_gain
    from policy.testing import smooth_episode

    if point == "release":
        with pytest.raises(ValueError, match="no episode with a release"):  # the smooth episodes only close
            point_gain(_Follower(1.0), run.parent / "data", point, episodes=4)
    data = tmp_path / "data"
    with ShardWriter(data, "w0") as w:
        for seed in range(3):
            ep = synthetic_episode("stack", seed)
            smooth_episode(ep, seed)
            ep.action[:int(0.3 * len(ep)), -1] = 0.0  # open until it closes on the object
            ep.action[int(0.8 * len(ep)):, -1] = 0.0  # let go near the end
            w.append(ep)
    full, half = (point_gain(_Follower(g, point), data, point, episodes=4) for g in (1.0, 0.5))
    assert full["samples"] > 0 and (full["x"], full["y"], full["off_cm"]) == (1.0, 1.0, 0.0)
    assert (half["x"], half["y"]) == (0.5, 0.5) and half["off_cm"] > 0
    assert point_gain(_Follower(0.0, point), data, point, episodes=4)["x"] == 0.0
    other = "grasp" if point == "release" else "release"  # a policy that follows only the other point
    assert point_gain(_Follower(1.0, other), data, point, episodes=4)["x"] == 0.0
    with pytest.raises(ValueError, match="expected 'release' or 'grasp'"):
        point_gain(_Follower(1.0), data, "goal")


def test_the_bundle_carries_the_gripper_levels_and_an_older_run_reads_them_from_its_data(run, bundle_dir, tmp_path):
    import shutil

    assert json.loads((bundle_dir / "manifest.json").read_text())["data"]["gripper_levels"] == [0.0, 1.0]
    old = tmp_path / "old"
    shutil.copytree(run, old)
    info = json.loads((old / "dataset.json").read_text())
    del info["gripper_levels"]  # as `sudd train` wrote it before it recorded them
    (old / "dataset.json").write_text(json.dumps(info))
    export(old, tmp_path / "b", cache_dir=CACHE)
    assert json.loads((tmp_path / "b" / "manifest.json").read_text())["data"]["gripper_levels"] == [0.0, 1.0]
    info["path"] = str(tmp_path / "gone")
    (old / "dataset.json").write_text(json.dumps(info))
    with pytest.raises(FileNotFoundError, match=r"records no gripper_levels and its data .*gone.* is gone"):
        export(old, tmp_path / "c", cache_dir=CACHE)

