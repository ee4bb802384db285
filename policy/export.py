"""Export a trained run to a self-contained policy bundle directory, verified before it is published.

    export("runs/pp", "bundles/pp")      # EMA weights of the latest checkpoint

Bundle layout (format "sudd-policy-bundle", version 1):

    manifest.json        format/version, opset, graph I/O (names, shapes, dtypes), horizons, dims, cameras and
                         image/crop size, tasks + known instructions, data content hash, config, DDIM schedule,
                         parameter counts, file sizes + sha256, text-encoder quantization and parity figures
    obs_encoder.onnx     image_<camera> uint8 (B,To,H,W,3) full frames, proprio (B,To,Dp) normalized,
                         text_embedding (B,384) -> cond (B,G); the centre crop and /255 are inside the graph
    denoiser.onnx        noisy_actions (B,Tp,Da), timestep (B,) int64, cond (B,G) -> noise_pred (B,Tp,Da)
    text_encoder.onnx    input_ids, attention_mask (B,L) int64 -> embedding (B,384), weight-only int8 MiniLM
    tokenizer/           tokenizer.json (+ vocab and configs) for `tokenizers`
    stats.npz            normalization (policy.normalize.STAT_KEYS)

One denoising step per graph, the DDIM loop in the loader (numpy), rather than the loop unrolled into one
graph with the noise as an input: measured on this 2-core CPU the two cost the same (16.7 vs 16.8 ms for
8 steps; onnxruntime's per-call overhead is ~20 us against ~2 ms of per-op work per step), and the step
graph is 8x smaller to load, can be checked step by step, and lets a deployment trade steps for speed.

The text encoder (90 MB fp32) is stored as weight-only int8 (23 MB; see policy.quantize for why not
onnxruntime's dynamic quantization) inside every bundle, so a bundle stays one self-contained directory a
robot can load offline. Exporting and quantizing it takes seconds and depends only on the MiniLM files and
the tool versions, so it is done once per cache key under $SUDD_CACHE_DIR (default ~/.cache/sudd) and
copied. Before anything is published, the bundle is loaded with `policy.bundle.Bundle` and compared with
torch on random inputs: each graph, every denoising step and the final action chunk (manifest "parity").
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from policy.config import TEXT_DIM, PolicyConfig
from policy.model import DiffusionPolicy, count_params, film_dim, prepare_images
from policy.normalize import STAT_KEYS, Normalizer
from policy.sampling import predict_chunk, schedule_for

FORMAT, FORMAT_VERSION, OPSET = "sudd-policy-bundle", 1, 17
STEP_TOL, CHUNK_TOL, TEXT_TOL, TEXT_MIN_COS = 1e-4, 1e-3, 1e-4, 0.99
SAMPLE_SENTENCES = [
    "pick up the red block and put it in the bowl", "grab the red cube and place it into the bowl",
    "stack the blue block on top of the green block", "open the top drawer", "close the drawer",
    "put the mug in the drawer and close it", "move the yellow block to the left of the plate",
    "the weather is lovely today", "what time does the train leave", "stop", "a",
]


class ExportError(RuntimeError):
    """The exported graphs do not reproduce the torch policy; nothing was published."""


def _onnx_export(module, args, path: Path, inputs: list[str], outputs: list[str], dynamic: dict, opset: int):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy (TorchScript) exporter's deprecation and tracer notes
        # dynamo=False: the torch.export-based exporter needs onnxscript, which this project does not ship
        torch.onnx.export(module, args, str(path), input_names=inputs, output_names=outputs, dynamic_axes=dynamic,
                          opset_version=opset, dynamo=False, do_constant_folding=True)


def _declare_io(path: Path, spec: dict) -> None:
    """Write the contract's shapes into the graph's declared inputs/outputs (the tracer leaves some output
    dims symbolic, e.g. a Concat's width), so onnxruntime reports exactly what the manifest says."""
    import onnx

    model = onnx.load(str(path))
    for values, specs in ((model.graph.input, spec["inputs"]), (model.graph.output, spec["outputs"])):
        by_name = {v.name: v for v in values}
        for io in specs:
            dims = by_name[io["name"]].type.tensor_type.shape.dim
            for d, want in zip(dims, io["shape"]):
                if isinstance(want, int):
                    d.dim_value = want
                else:
                    d.dim_param = want
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _io(name: str, shape: list, dtype: str) -> dict:
    return {"name": name, "shape": shape, "dtype": dtype}


def graph_specs(cfg: PolicyConfig) -> dict:
    """The I/O contract of every graph, as written to the manifest and checked by the loader."""
    To, Tp, Da, Dp, G = cfg.obs_horizon, cfg.pred_horizon, cfg.action_dim, cfg.proprio_dim, film_dim(cfg)
    H, W = cfg.image_size
    return {
        "obs_encoder": {"file": "obs_encoder.onnx",
                        "inputs": [_io(f"image_{c}", ["B", To, H, W, 3], "uint8") for c in cfg.cameras]
                        + [_io("proprio", ["B", To, Dp], "float32"), _io("text_embedding", ["B", TEXT_DIM], "float32")],
                        "outputs": [_io("cond", ["B", G], "float32")]},
        "denoiser": {"file": "denoiser.onnx",
                     "inputs": [_io("noisy_actions", ["B", Tp, Da], "float32"), _io("timestep", ["B"], "int64"),
                                _io("cond", ["B", G], "float32")],
                     "outputs": [_io("noise_pred", ["B", Tp, Da], "float32")]},
        "text_encoder": {"file": "text_encoder.onnx",
                         "inputs": [_io("input_ids", ["B", "L"], "int64"), _io("attention_mask", ["B", "L"], "int64")],
                         "outputs": [_io("embedding", ["B", TEXT_DIM], "float32")]},
    }


class _ObsGraph(torch.nn.Module):
    """obs_encoder.onnx: raw uint8 frames per camera, proprio, text -> cond = the denoiser's FiLM input
    computed from the global cond once per chunk (ConditionalUnet1D.condition)."""

    def __init__(self, model: DiffusionPolicy):
        super().__init__()
        self.model, self.cameras, self.crop = model, model.cfg.cameras, model.cfg.crop_size

    def forward(self, *args):
        images = {c: prepare_images(x, self.crop) for c, x in zip(self.cameras, args)}
        return self.model.unet.condition(self.model.encode(images, args[-2], args[-1]))


class _StepGraph(torch.nn.Module):
    """denoiser.onnx: one denoising step from the precomputed FiLM cond (ConditionalUnet1D.denoise)."""

    def __init__(self, model: DiffusionPolicy):
        super().__init__()
        self.unet = model.unet

    def forward(self, noisy, timestep, cond):
        return self.unet.denoise(noisy, timestep, cond)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def cache_root(cache_dir: str | Path | None = None) -> Path:
    return Path(cache_dir or os.environ.get("SUDD_CACHE_DIR") or Path.home() / ".cache" / "sudd")


def text_encoder_onnx(cache_dir: str | Path | None = None, opset: int = OPSET) -> tuple[Path, dict]:
    """The weight-only-int8 MiniLM graph (exported, checked and quantized once per cache key) and its figures."""
    import onnx
    import onnxruntime as ort

    from policy.quantize import weight_only_int8
    from policy.text import SentenceEmbedder, model_dir, tokenize

    src = model_dir()
    key = hashlib.sha256(f"{_sha256(src / 'model.safetensors')}|{opset}|{torch.__version__}|{onnx.__version__}|"
                         f"wo-int8-v1".encode()).hexdigest()[:16]
    out = cache_root(cache_dir) / "text_encoder" / key
    if (out / "info.json").is_file() and (out / "text_encoder.onnx").is_file():
        return out / "text_encoder.onnx", json.loads((out / "info.json").read_text())
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
    return out / "text_encoder.onnx", info


def export(run_dir: str | Path, out_bundle_dir: str | Path, checkpoint: str | Path | None = None, ema: bool = True,
           opset: int = OPSET, cache_dir: str | Path | None = None) -> dict:
    """Export a training run (latest checkpoint, EMA weights) to a bundle directory; returns the manifest."""
    from policy.train import load_run_model

    run_dir = Path(run_dir)
    model, cfg, training = load_run_model(run_dir, checkpoint, ema)
    normalizer = Normalizer.load(run_dir / "stats.npz")
    data_info = json.loads((run_dir / "dataset.json").read_text())
    return export_model(model, normalizer, out_bundle_dir, data_info, training, opset, cache_dir)


def export_model(model: DiffusionPolicy, normalizer: Normalizer, out_bundle_dir: str | Path,
                 data_info: dict | None = None, training: dict | None = None, opset: int = OPSET,
                 cache_dir: str | Path | None = None) -> dict:
    """Write, verify and publish the bundle of `model` (atomically: a failed export leaves no bundle)."""
    import tokenizers

    from policy.text import TOKENIZER_FILES, MAX_SEQ_LENGTH, model_dir

    model = model.eval().cpu()
    cfg = model.cfg
    out = Path(out_bundle_dir)
    if out.exists() and any(out.iterdir()) and not (out / "manifest.json").is_file():
        raise FileExistsError(f"{out} exists and is not a policy bundle; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.partial-"))
    try:
        specs = graph_specs(cfg)
        g = torch.Generator().manual_seed(0)
        H, W = cfg.image_size
        ex_imgs = [torch.randint(0, 256, (1, cfg.obs_horizon, H, W, 3), generator=g, dtype=torch.uint8)
                   for _ in cfg.cameras]
        ex_p, ex_t = torch.randn(1, cfg.obs_horizon, cfg.proprio_dim), torch.randn(1, TEXT_DIM)
        names = lambda s, k: [i["name"] for i in s[k]]  # noqa: E731
        so = specs["obs_encoder"]
        _onnx_export(_ObsGraph(model), (*ex_imgs, ex_p, ex_t), tmp / so["file"], names(so, "inputs"),
                     names(so, "outputs"), {n: {0: "B"} for n in names(so, "inputs") + names(so, "outputs")}, opset)
        _declare_io(tmp / so["file"], so)
        sd = specs["denoiser"]
        with torch.no_grad():
            cond = _ObsGraph(model)(*ex_imgs, ex_p, ex_t)
        _onnx_export(_StepGraph(model), (torch.randn(1, cfg.pred_horizon, cfg.action_dim), torch.tensor([5]), cond),
                     tmp / sd["file"], names(sd, "inputs"), names(sd, "outputs"),
                     {n: {0: "B"} for n in names(sd, "inputs") + names(sd, "outputs")}, opset)
        _declare_io(tmp / sd["file"], sd)
        text_path, text_info = text_encoder_onnx(cache_dir, opset)
        shutil.copyfile(text_path, tmp / "text_encoder.onnx")
        (tmp / "tokenizer").mkdir()
        for name in TOKENIZER_FILES:
            shutil.copyfile(model_dir() / name, tmp / "tokenizer" / name)
        normalizer.save(tmp / "stats.npz")
        files = [p for p in sorted(tmp.rglob("*")) if p.is_file()]
        data_info = data_info or {}
        manifest = {
            "format": FORMAT, "format_version": FORMAT_VERSION, "opset": opset,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "producer": {"torch": torch.__version__, "tokenizers": tokenizers.__version__},
            "horizons": {"obs": cfg.obs_horizon, "pred": cfg.pred_horizon, "action": cfg.action_horizon,
                         "execute_from": cfg.obs_horizon - 1, "control_hz": 10.0},
            "dims": {"proprio": cfg.proprio_dim, "action": cfg.action_dim, "text": TEXT_DIM,
                     "cond": film_dim(cfg), "global_cond": cfg.global_cond_dim},
            "action_layout": {"position": [0, 3], "rot6d": [3, 9], "gripper": [9, 10]},
            "cameras": list(cfg.cameras), "image_size": list(cfg.image_size), "crop_size": list(cfg.crop_size),
            "graphs": specs,
            "tokenizer": {"dir": "tokenizer", "file": "tokenizer/tokenizer.json", "max_length": MAX_SEQ_LENGTH},
            "stats": {"file": "stats.npz", "keys": list(STAT_KEYS)},
            "diffusion": {"num_train_timesteps": cfg.num_train_timesteps, "beta_schedule": cfg.beta_schedule,
                          "prediction_type": "epsilon", "sampler": "ddim", "eta": 0.0,
                          "clip_sample": cfg.clip_sample, "spacing": "trailing"},
            "ddim": schedule_for(model),
            "tasks": data_info.get("tasks", []), "instructions": data_info.get("instructions", []),
            "data": {k: v for k, v in data_info.items() if k not in ("tasks", "instructions")},
            "training": training or {}, "config": cfg.to_dict(),
            "params": {"obs_encoder": count_params(model.obs_encoder) + count_params(model.unet.film_cond),
                       "denoiser": count_params(model.unet) - count_params(model.unet.film_cond),
                       "policy_total": count_params(model), "text_encoder": text_info["params"]},
            "text_encoder": text_info,
            "files": {str(p.relative_to(tmp)): {"bytes": p.stat().st_size, "sha256": _sha256(p)} for p in files},
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        manifest["parity"] = check_parity(model, normalizer, tmp)
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest


def check_parity(model: DiffusionPolicy, normalizer: Normalizer, bundle_dir: str | Path, trials: int = 3,
                 seed: int = 0) -> dict:
    """torch vs the bundle on random observations: cond, every denoising step along the bundle's own DDIM
    trajectory, and the final absolute action chunk from the same noise. Raises ExportError over tolerance."""
    from policy.bundle import Bundle

    b = Bundle.load(bundle_dir, warmup=False)
    cfg, rng = model.cfg, np.random.default_rng(seed)
    worst = {"cond_max_abs_err": 0.0, "step_max_abs_err": 0.0, "chunk_max_abs_err": 0.0}
    for _ in range(trials):
        H, W = cfg.image_size
        images = {c: rng.integers(0, 256, (cfg.obs_horizon, H, W, 3), dtype=np.uint8) for c in cfg.cameras}
        lo, hi = normalizer.proprio_min, normalizer.proprio_max
        proprio = (lo + (hi - lo) * rng.random((cfg.obs_horizon, cfg.proprio_dim))).astype(np.float32)
        text = rng.normal(size=TEXT_DIM).astype(np.float32)
        text /= np.linalg.norm(text)
        noise = rng.normal(size=(cfg.pred_horizon, cfg.action_dim)).astype(np.float32)
        trace: list = []
        chunk = b.act(images, proprio, text, noise=noise, trace=trace)
        with torch.no_grad():
            imgs = {c: prepare_images(torch.from_numpy(images[c])[None], cfg.crop_size) for c in cfg.cameras}
            cond = model.unet.condition(model.encode(imgs, torch.from_numpy(normalizer.normalize_proprio(proprio))[None],
                                                     torch.from_numpy(text)[None]))
            worst["cond_max_abs_err"] = max(worst["cond_max_abs_err"], float(np.abs(cond.numpy() - trace[0]).max()))
            for x, t, eps in trace[1:]:
                ref = model.unet.denoise(torch.from_numpy(x), torch.tensor([t]), torch.from_numpy(trace[0]))
                worst["step_max_abs_err"] = max(worst["step_max_abs_err"], float(np.abs(ref.numpy() - eps).max()))
        ref_chunk = predict_chunk(model, normalizer, images, proprio, text, noise)
        worst["chunk_max_abs_err"] = max(worst["chunk_max_abs_err"], float(np.abs(ref_chunk - chunk).max()))
    worst.update(trials=trials, step_tol=STEP_TOL, chunk_tol=CHUNK_TOL)
    if worst["step_max_abs_err"] > STEP_TOL or worst["cond_max_abs_err"] > STEP_TOL or worst["chunk_max_abs_err"] > CHUNK_TOL:
        raise ExportError(f"exported graphs disagree with torch: {worst}")
    return worst
