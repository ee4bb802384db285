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

For a bundle that takes a release point (release_input: the goal query's) or a grasp point (grasp_input: the
object query's), `point_gain` says how far the chunk follows it: on frames shortly before a recorded release
(or close), the recorded point is given, then the same moved 3 cm along x and along y, and the chunk's action at
that step moves by gain x 3 cm (1: it goes where it is told; 0: the images decide, whatever the query says).
The five-family bundle of 2026-11 followed its release point 0.5-0.6, trained with 2.5 cm of noise on it.
"""

from __future__ import annotations

import json
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


def point_gain(bundle, data_dir: str | Path, point: str = "release", episodes: int = 24, seed: int = 0,
               shift_m: float = 0.03) -> dict:
    """How far the chunk follows a given release or grasp point (see the module docstring): the median gain
    along x and y, and how far (cm, xy, median) the chunk's action at the event's step is from the recorded
    point. The event is each episode's last let-go for "release" and every close for "grasp" (drawer_put's
    object is its second close, the one the object query serves)."""
    from datagen.store import Dataset

    if point not in ("release", "grasp"):
        raise ValueError(f"point {point!r}: expected 'release' or 'grasp'")
    store, rng = Dataset(data_dir), np.random.default_rng(seed)
    rows = store.episodes()
    gains: dict[str, list[float]] = {"x": [], "y": []}
    off = []
    for r in rng.permutation(len(rows))[:episodes]:
        i = int(rows[int(r)]["index"])
        w = store.window(i, fields=("action", "proprio", *(f"{c}_rgb" for c in bundle.cameras)))
        shut = w["action"][:, -1] > 0.5
        edges = np.flatnonzero(shut[1:] != shut[:-1]) + 1  # the steps where the gripper command flips
        events = edges[shut[edges]] if point == "grasp" else edges[~shut[edges]][-1:]
        emb = bundle.embed(store.meta(i)["instruction"])
        for to in (int(e) for e in events if e >= 2):
            target = w["action"][to, :3]
            for t in range(max(0, to - 8), to - 1, 3):  # 0.8-0.2 s before it, on the way there
                window = np.clip(np.arange(t - bundle.obs_horizon + 1, t + 1), 0, None)  # the first frame repeats
                images = {c: w[f"{c}_rgb"][window] for c in bundle.cameras}
                z = rng.standard_normal((bundle.pred_horizon, bundle.action_dim))
                k = min(bundle.pred_horizon - 1, to - t)

                def chunk(at):
                    return bundle.act(images, w["proprio"][window], emb, noise=z, **{point: np.append(at, 1.0)})[k]

                base = chunk(target)
                off.append(float(np.linalg.norm(base[:2] - target[:2])) * 100)
                for j, axis in enumerate("xy"):
                    gains[axis].append(float(chunk(target + shift_m * np.eye(3)[j])[j] - base[j]) / shift_m)
    if not off:
        what = "a release" if point == "release" else "a close"
        raise ValueError(f"{data_dir}: no episode with {what} to measure the {point} gain on")
    return {"samples": len(off), "x": round(float(np.median(gains["x"])), 2),
            "y": round(float(np.median(gains["y"])), 2), "off_cm": round(float(np.median(off)), 2)}


def blind_cameras(figures: dict, ratio: float = 0.2) -> list[str]:
    """Cameras whose swap moves the chunk less than `ratio` x the noise spread: the policy ignores them."""
    noise = figures.get("noise", 0.0)
    return [k[6:] for k, v in figures.items() if k.startswith("image_") and v < ratio * noise]


def record_in_manifest(bundle_dir: Path, manifest: dict, quiet: bool) -> None:
    """Add policy.sensitivity's figures to the manifest when the run's data is at hand, and say if the
    policy ignores a camera (a blind policy drives to the average target)."""
    from policy.bundle import Bundle

    data = (manifest.get("data") or {}).get("path")
    if not data or not Path(data).is_dir():
        if not quiet:
            print(f"input sensitivity: skipped (the run's data {data!r} is not here)")
        return
    bundle = Bundle.load(bundle_dir, intra_op_num_threads=1)
    figures = manifest["input_sensitivity"] = input_sensitivity(bundle, data)
    gains = {}
    for point, given in (("release", bundle.release_input), ("grasp", bundle.grasp_input)):
        if not given:
            continue
        try:
            gains[point] = manifest[f"{point}_gain"] = point_gain(bundle, data, point)
        except ValueError as exc:  # data without that event (e.g. the gripper never opens): nothing to measure
            if not quiet:
                print(f"{point} gain: skipped ({exc})")
    (bundle_dir / "manifest.json").write_text(json.dumps(manifest, indent=2))
    if quiet:
        return
    shown = ", ".join(f"{k} {v:.1f}" for k, v in figures.items() if k not in ("samples", "unit"))
    print(f"input sensitivity (mm the executed chunk moves when one input is swapped): {shown}")
    for point, gain in gains.items():
        print(f"{point} gain (how far the chunk follows a given {point} point, 1 = all the way): x {gain['x']:.2f}, "
              f"y {gain['y']:.2f}; {gain['off_cm']:.1f} cm off the recorded one at its step")
    blind = blind_cameras(figures)
    if blind:
        print(f"warning: the policy ignores camera(s) {', '.join(blind)}: swapping them moves the chunk less than "
              "a fifth of its own sampling spread. It will follow proprioception to the average target; train "
              "longer or change the image encoder (policy/sensitivity.py says more).")
