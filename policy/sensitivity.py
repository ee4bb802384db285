"""Which inputs a policy bundle actually uses: swap one input for another sample's and see the chunk move.

A diffusion policy can reach a low training loss while ignoring its cameras: proprioception over the
observation window says where the arm is going, so the only thing the images add is *which* object and
*where*, a small part of the loss. Such a policy looks fine open loop and drives to the average target in
closed loop. This check makes that visible in numbers, on the policy's own training data:

    for each of N sampled observation windows (i) and another window from a different episode (j):
        base     = act(images_i, proprio_i, text_i, noise z_i)
        swap X   = the same with input X taken from j          (X = each camera, proprio, text)
        noise    = the same inputs with other noise            (the policy's own spread, for scale)
    figure = mean over samples of the mean distance between the executed TCP positions, in mm

A camera whose figure is near 0 (well under `noise`) is not used. `sudd export` records the figures in
the bundle manifest ("input_sensitivity") when the run's data is at hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _windows(store, rng: np.random.Generator, n: int, To: int, cameras) -> list[dict]:
    rows = store.episodes()
    picks = rng.choice(len(rows), size=min(n, len(rows)), replace=False)
    out = []
    for r in picks:
        i = int(rows[int(r)]["index"])
        T = int(rows[int(r)]["length"])
        t = int(rng.integers(0, T))
        lo = max(0, t - To + 1)
        w = store.window(i, lo, t + 1, fields=("proprio", *(f"{c}_rgb" for c in cameras)))
        pad = np.clip(np.arange(t - To + 1, t + 1) - lo, 0, None)  # the first frame repeats before the start
        out.append({"episode": i, "instruction": store.meta(i)["instruction"], "proprio": w["proprio"][pad],
                    "images": {c: w[f"{c}_rgb"][pad] for c in cameras}})
    return out


def input_sensitivity(bundle, data_dir: str | Path, samples: int = 24, seed: int = 0) -> dict:
    """Mean change (mm) of the executed TCP positions when each input is swapped; see the module docstring."""
    from datagen.store import Dataset

    rng = np.random.default_rng(seed)
    wins = _windows(Dataset(data_dir), rng, samples, bundle.obs_horizon, bundle.cameras)
    if len(wins) < 2:
        raise ValueError(f"{data_dir}: need at least 2 episodes to swap inputs between")
    emb = {w["instruction"]: bundle.embed(w["instruction"]) for w in wins}
    ex = bundle.execute
    groups = [f"image_{c}" for c in bundle.cameras] + ["proprio", "text", "noise"]
    moved: dict[str, list[float]] = {g: [] for g in groups}
    for k, a in enumerate(wins):
        b = wins[(k + 1 + int(rng.integers(0, len(wins) - 1))) % len(wins)]
        z = rng.standard_normal((bundle.pred_horizon, bundle.action_dim))
        base = bundle.act(a["images"], a["proprio"], emb[a["instruction"]], noise=z)[ex, :3]
        for g in groups:
            images, proprio, text, noise = dict(a["images"]), a["proprio"], emb[a["instruction"]], z
            if g.startswith("image_"):
                images[g[6:]] = b["images"][g[6:]]
            elif g == "proprio":
                proprio = b["proprio"]
            elif g == "text":
                text = emb[b["instruction"]]
            else:
                noise = rng.standard_normal(z.shape)
            got = bundle.act(images, proprio, text, noise=noise)[ex, :3]
            moved[g].append(float(np.linalg.norm(got - base, axis=1).mean()) * 1e3)
    return {"samples": len(wins), "unit": "mm (mean executed TCP position change)",
            **{g: round(float(np.mean(v)), 2) for g, v in moved.items()}}


def blind_cameras(figures: dict, ratio: float = 0.2) -> list[str]:
    """Cameras whose swap moves the chunk less than `ratio` x the noise spread: the policy ignores them."""
    noise = figures.get("noise", 0.0)
    return [k[6:] for k, v in figures.items() if k.startswith("image_") and v < ratio * noise]
