"""The scripted-oracle demo: every task family solved under domain randomization, saved as PNG strips.

This is `make demo` until a trained policy ships: it shows the world, the tasks, the randomization and
that every task is solvable in this physics, with the success predicate's verdict for each episode.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from sim.build import build_episode
from sim.render import CameraRenderer
from sim.tasks import task_names


def run_oracle_episode(task: str, seed: int, dr: str, fidelity: str, frames: int = 8, size=(320, 240)):
    """Run the oracle once; returns (success, sim seconds, wall seconds, list of frames, instruction)."""
    ep = build_episode(task, seed, dr, fidelity)
    world = ep.world
    shots: list[np.ndarray] = []
    every = 1.0  # seconds of sim time between frames; trimmed to `frames` afterwards
    next_t = [0.0]
    with CameraRenderer(world, *size, shadows=fidelity == "full") as cams:
        def observe(w):
            if w.time >= next_t[0]:
                shots.append(cams.rgb("scene_cam"))
                next_t[0] += every
        t0 = time.perf_counter()
        shots.append(cams.rgb("scene_cam"))
        ep.task.oracle(world, ep.instance, observer=observe)
        wall = time.perf_counter() - t0
        shots.append(cams.rgb("scene_cam"))
    idx = np.linspace(0, len(shots) - 1, min(frames, len(shots))).round().astype(int)
    return ep.success(), world.time, wall, [shots[i] for i in idx], ep.instruction


def strip(images: list[np.ndarray], caption: str, ok: bool, per_row: int = 4) -> Image.Image:
    """The episode's frames left to right, top to bottom, under a caption with the verdict."""
    h, w = images[0].shape[:2]
    rows = -(-len(images) // per_row)
    canvas = Image.new("RGB", (w * min(per_row, len(images)), h * rows + 22), (20, 20, 20))
    for i, img in enumerate(images):
        canvas.paste(Image.fromarray(img), ((i % per_row) * w, 22 + (i // per_row) * h))
    draw = ImageDraw.Draw(canvas)
    draw.text((6, 5), f"{'SUCCESS' if ok else 'FAILED'}  {caption}", fill=(120, 230, 120) if ok else (240, 110, 110))
    return canvas


def run_demo(out: Path, tasks: list[str] | None = None, seed: int = 0, dr: str = "heavy",
             fidelity: str = "full") -> dict:
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in tasks or task_names():
        ok, sim_s, wall_s, images, text = run_oracle_episode(name, seed, dr, fidelity)
        path = out / f"{name}_seed{seed}.png"
        strip(images, f"{name} (seed {seed}, DR {dr}): \"{text}\"", ok).save(path)
        results[name] = {"instruction": text, "success": ok, "sim_seconds": round(sim_s, 2),
                         "wall_seconds": round(wall_s, 2), "strip": str(path)}
        print(f"  {'ok  ' if ok else 'FAIL'} {name:13s} \"{text}\"  ({sim_s:.1f} s sim, {wall_s:.1f} s wall) -> {path}",
              flush=True)
    (out / "summary.json").write_text(json.dumps(results, indent=2))
    return results
