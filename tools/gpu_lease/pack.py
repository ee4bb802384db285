"""Pack what a lease's box needs from here into .gpu/ (kept small: the transfer's limit is 64 MiB in all).

usage: python tools/gpu_lease/pack.py PRETRAIN_RUN [BUNDLE]
- .gpu/<run name>/: the pretrain run's config, dataset and stats, and a checkpoint holding only the EMA weights
  of the modules a warm start takes from it (policy.warm_start.PRETRAINED), in float16 (half the bytes; the
  exported bundle rounds its weights to float16 anyway);
- .gpu/text_encoder.onnx.xz and .gpu/tokenizer/: BUNDLE's text encoder (default policy/bundles/demo), which
  `sudd export --text-encoder-from` copies on a box without the MiniLM package (xz: 23 -> 21 MB).
"""
import lzma
import shutil
import sys
from pathlib import Path

import torch

from policy.train import latest_checkpoint
from policy.warm_start import PRETRAINED


def main() -> None:
    run, bundle = Path(sys.argv[1]), Path(sys.argv[2] if len(sys.argv) > 2 else "policy/bundles/demo")
    dst = Path(".gpu") / run.name
    (dst / "checkpoints").mkdir(parents=True, exist_ok=True)
    for f in ("config.json", "dataset.json", "stats.npz"):
        shutil.copy(run / f, dst / f)
    ck = latest_checkpoint(run)
    s = torch.load(ck, map_location="cpu", weights_only=False)
    ema = {k: v.half() if v.is_floating_point() else v for k, v in s["ema"]["model"].items()
           if k.startswith(tuple(p + "." for p in PRETRAINED))}
    torch.save({"step": s["step"], "total_steps": s["total_steps"], "model": ema, "ema": {"model": ema, "updates": 0},
                "config": s["config"], "torch": s["torch"]}, dst / "checkpoints" / ck.name)
    with open(bundle / "text_encoder.onnx", "rb") as f, lzma.open(".gpu/text_encoder.onnx.xz", "wb") as g:
        shutil.copyfileobj(f, g)
    shutil.copytree(bundle / "tokenizer", ".gpu/tokenizer", dirs_exist_ok=True)
    print(f"{dst} ({sum(v.numel() for v in ema.values()) / 1e6:.1f} M parameters, float16), "
          f".gpu/text_encoder.onnx.xz and .gpu/tokenizer from {bundle}")


if __name__ == "__main__":
    main()
