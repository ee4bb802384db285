"""Copy a run's newest checkpoint as EMA weights only (if they fit the 16 MiB a file, in float16 where float32
does not: `full`'s do not at all) and its small files to $OUT."""
import os
import sys
import tarfile
from pathlib import Path

import torch

run = Path(sys.argv[1])
dst = Path(os.environ["OUT"])
ck = sorted((run / "checkpoints").glob("step_*.pt"))
if ck:
    s = torch.load(ck[-1], map_location="cpu", weights_only=False)
    ema = s["ema"]["model"]  # "model" shares its storage: saved once
    size = sum(v.numel() * v.element_size() for v in ema.values())
    if 15 * 2**20 < size <= 30 * 2**20:  # float16 fits: loading it back casts it to the model's float32
        from pack import float16_weights  # this script's folder is on sys.path

        ema = float16_weights(run, ema)
        size //= 2
    if size > 15 * 2**20:
        print(f"{run.name}: EMA weights {size / 2**20:.0f} MiB, over the 16 MiB a file: left on the box")
    else:
        torch.save({"step": s["step"], "total_steps": s["total_steps"], "model": ema,
                    "ema": {"model": ema, "updates": 0}, "config": s["config"], "torch": s["torch"]},
                   dst / f"{run.name}.pt")
        print("pulled", run.name, ck[-1].name)
with tarfile.open(dst / f"{run.name}.tar", "w") as tar:
    for f in ("config.json", "stats.npz", "dataset.json", "warm_start.json", "metrics.jsonl", "plan.json",
              "summary.json", "DONE"):
        if (run / f).exists():
            tar.add(run / f, arcname=f)
