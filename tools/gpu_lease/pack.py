"""Pack what a lease's box needs from here into .gpu/ (kept small: the transfer's limit is 64 MiB in all).

usage: python tools/gpu_lease/pack.py [RUN ...] [--bundle BUNDLE] [--text-encoder BUNDLE]
- .gpu/<run name>/: each run's config, dataset and stats, and a checkpoint holding only its EMA weights in
  float16 (half the bytes; the exported bundle rounds its weights to float16 anyway; buffers stay float32): of
  a `sudd pretrain` run only the modules a warm start takes from it (policy.warm_start.PRETRAINED), of a policy
  run all of them (the box then goes on training it: `"init_from"` in the variant);
- with --bundle: .gpu/<bundle name>/, a committed bundle's weights as such a run (policy.bundle_import rebuilds
  the torch model from its graphs here, where its text encoder is; the box, without one, could not load it);
- with --text-encoder: .gpu/text_encoder.onnx.xz and .gpu/tokenizer/, BUNDLE's text encoder (policy/bundles/demo),
  which `sudd export --text-encoder-from` copies on a box without the MiniLM package (xz: 23 -> 21 MB). Only a
  box that exports needs it; a lease whose weights come back to be exported here leaves it behind.
"""
import argparse
import lzma
import shutil
from pathlib import Path

import torch

from policy.train import latest_checkpoint, load_run_model
from policy.warm_start import PRETRAINED, is_pretrain_run


def float16_weights(run: Path, state: dict) -> dict:
    """`state` (a checkpoint's tensors of `run`'s model) with its float weights in float16 and its buffers as they
    are: the proprio stats in them must stay the run's stats.npz, which a warm start takes (rounded, a bundle's
    graphs disagree with its stats by 1e-3 and `bundle_import` refuses to rebuild it). pull.py uses it too."""
    return half_weights(load_run_model(run)[0], state)


def half_weights(model: torch.nn.Module, state: dict) -> dict:
    """`state` with its float tensors in float16, except `model`'s buffers (see float16_weights)."""
    buffers = {name for name, _ in model.named_buffers()}
    return {k: v.half() if v.is_floating_point() and k not in buffers else v for k, v in state.items()}


def pack_run(run: Path) -> Path:
    dst = Path(".gpu") / run.name
    if dst.exists():
        shutil.rmtree(dst)  # an older pack's checkpoint of another step would be the one taken
    (dst / "checkpoints").mkdir(parents=True)
    for f in ("config.json", "dataset.json", "stats.npz"):
        shutil.copy(run / f, dst / f)
    ck = latest_checkpoint(run)
    s = torch.load(ck, map_location="cpu", weights_only=False)
    keep = tuple(p + "." for p in PRETRAINED) if is_pretrain_run(run) else ("",)
    ema = float16_weights(run, {k: v for k, v in s["ema"]["model"].items() if k.startswith(keep)})
    torch.save({"step": s["step"], "total_steps": s["total_steps"], "model": ema, "ema": {"model": ema, "updates": 0},
                "config": s["config"], "torch": s["torch"]}, dst / "checkpoints" / ck.name)
    print(f"{dst}: {sum(v.numel() for v in ema.values()) / 1e6:.1f} M parameters of {ck.name}, float16")
    return dst


def pack_bundle(bundle: Path) -> Path:
    import json

    from policy.bundle_import import model_from_bundle

    model, normalizer, manifest = model_from_bundle(bundle)
    dst = Path(".gpu") / bundle.name
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "checkpoints").mkdir(parents=True)
    (dst / "config.json").write_text(json.dumps(manifest["config"], indent=2))
    (dst / "dataset.json").write_text(json.dumps(manifest["data"], indent=2))
    normalizer.save(dst / "stats.npz")
    ema = half_weights(model, model.state_dict())
    step = int(manifest["training"]["step"])
    torch.save({"step": step, "total_steps": step, "model": ema, "ema": {"model": ema, "updates": 0},
                "config": manifest["config"], "torch": torch.__version__}, dst / "checkpoints" / f"step_{step:08d}.pt")
    print(f"{dst}: {bundle}'s weights (parity {manifest['imported']['parity']['chunk_max_abs_err']:.1e}), float16")
    return dst


def pack_text_encoder(bundle: Path) -> None:
    with open(bundle / "text_encoder.onnx", "rb") as f, lzma.open(".gpu/text_encoder.onnx.xz", "wb") as g:
        shutil.copyfileobj(f, g)
    shutil.copytree(bundle / "tokenizer", ".gpu/tokenizer", dirs_exist_ok=True)
    print(f".gpu/text_encoder.onnx.xz and .gpu/tokenizer from {bundle}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="*", type=Path)
    p.add_argument("--bundle", type=Path, help="a bundle's weights, packed as a run")
    p.add_argument("--text-encoder", type=Path, metavar="BUNDLE")
    a = p.parse_args()
    for run in a.runs:
        pack_run(run)
    if a.bundle:
        pack_bundle(a.bundle)
    if a.text_encoder:
        pack_text_encoder(a.text_encoder)


if __name__ == "__main__":
    main()
