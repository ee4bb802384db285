"""One training run on the lent box: policy.train.train with the precomputed embeddings and a step count
fitted to the time left. usage: python train.py DATA RUN_DIR DEADLINE_EPOCH_S OVERRIDES_JSON
OVERRIDES_JSON may name "config" (a preset, .toml or bundle), "base" (a run's config.json whose values come
first, under the lease's and the variant's), "init_from" (a run to warm-start from) and "encoders_from" (with
init_from, a pretrain run whose encoders and aux head replace init_from's)."""
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, os.getcwd())
from policy.train import train  # noqa: E402

CONFIG = "policy/configs/demo_pick_place.toml"  # a variant's "config" key names another


def main() -> None:
    data, out, deadline, extra = sys.argv[1], Path(sys.argv[2]), float(sys.argv[3]), json.loads(sys.argv[4])
    tab = np.load(".gpu/texts.npz")
    row = {t: i for i, t in enumerate(tab["texts"].tolist())}

    def embed(texts):
        missing = [t for t in texts if t not in row]
        if missing:
            raise KeyError(f"{len(missing)} texts were not embedded ahead (texts.py), e.g. {missing[:3]}")
        return tab["table"][[row[t] for t in texts]]

    config = extra.pop("config", CONFIG)
    base = extra.pop("base", None)  # a run's config.json (.gpu/run_famfz_w2): its choices under the lease's
    base = json.loads(Path(base).read_text()) if base else {}
    init_from = extra.pop("init_from", None)  # a run directory carried along (.gpu/run_pre3: the pretrained encoders)
    encoders_from = extra.pop("encoders_from", None)
    device = "cuda" if torch.cuda.is_available() else "cpu"  # cpu: a dry run of the scripts
    steps = extra.pop("steps", None)  # known from an earlier lease: no probe leg (it loads the data twice)
    ov = {**base, "batch_size": 256, "lr": 5e-4, "warmup_steps": 500, "num_workers": 7, "amp": device == "cuda",
          "checkpoint_every": 1000, "keep_checkpoints": 2, "log_every": 50, "val_fraction": 0.05, "val_every": 2000,
          **extra}
    warm = {"init_from": init_from, "encoders_from": encoders_from}
    plan = {"steps": steps, "overrides": ov}
    if not steps:
        # a short first leg measures the speed (warm-up only, so the schedule's length does not matter yet)
        probe, t0 = int(os.environ.get("LEASE_PROBE_STEPS", 300)), time.time()
        train(data, config, out, steps=10**6, stop_at=probe, embedder=embed, overrides=ov, device=device,
              progress=True, **warm)
        rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
        rates = [r["steps_per_s"] for r in rows if "steps_per_s" in r]  # validation rows have none
        rate = float(np.median(rates[len(rates) // 2:]))
        load_s = time.time() - t0 - probe / rate
        steps = int(max(probe + 100, rate * (deadline - time.time() - load_s - 30)))
        plan = {"rate": rate, "load_s": load_s, "steps": steps, "overrides": ov}
        (out / "plan.json").write_text(json.dumps(plan))
        warm = {}  # the main leg resumes the probe's checkpoint
    print(out.name, json.dumps(train(data, config, out, steps=int(steps), embedder=embed, overrides=ov,
                                     device=device, progress=True, **warm)), flush=True)
    (out / "plan.json").write_text(json.dumps(plan))
    (out / "DONE").write_text("ok")

if __name__ == "__main__":
    main()
