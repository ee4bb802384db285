"""Training curves (loss on a log axis, learning rate) from metrics.jsonl to a PNG.

matplotlib when it is installed; otherwise a small Pillow line plot (Pillow is a project dependency and
matplotlib is not), so every run ends with a picture without adding a dependency.
"""

from __future__ import annotations

import json
import math
from pathlib import Path


def read_metrics(path: str | Path) -> list[dict]:
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_metrics(metrics_path: str | Path, out_png: str | Path) -> Path | None:
    rows = [r for r in read_metrics(metrics_path) if "loss" in r]
    if not rows:
        return None
    steps = [r["step"] for r in rows]
    series = [("loss", [r["loss"] for r in rows], True), ("lr", [r["lr"] for r in rows], False)]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
        for ax, (name, ys, log) in zip(axes, series):
            ax.plot(steps, ys)
            ax.set_ylabel(name)
            if log:
                ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[-1].set_xlabel("step")
        fig.tight_layout()
        fig.savefig(out_png, dpi=100)
        plt.close(fig)
    except ImportError:
        _pil_plot(steps, series, out_png)
    return Path(out_png)


def _pil_plot(steps: list[int], series: list[tuple[str, list[float], bool]], out_png: str | Path) -> None:
    from PIL import Image, ImageDraw

    W, H, pad = 800, 500, 50
    img = Image.new("RGB", (W, H), "white")
    draw = ImageDraw.Draw(img)
    panel_h = (H - pad) // len(series)
    x0, x1 = min(steps), max(steps) if max(steps) > min(steps) else min(steps) + 1
    for k, (name, raw, log) in enumerate(series):
        top, bottom = k * panel_h + 20, (k + 1) * panel_h - 10
        ys = [math.log10(max(y, 1e-12)) for y in raw] if log else raw
        lo, hi = min(ys), max(ys)
        hi = hi if hi > lo else lo + 1e-12
        draw.rectangle([pad, top, W - 20, bottom], outline="gray")
        draw.text((pad + 5, top + 3), f"{name}{' (log axis)' if log else ''}: last {raw[-1]:.4g}, "
                  f"range {min(raw):.3g}..{max(raw):.3g}", fill="black")
        pts = [(pad + (s - x0) / (x1 - x0) * (W - 20 - pad), bottom - (y - lo) / (hi - lo) * (bottom - top - 15))
               for s, y in zip(steps, ys)]
        if len(pts) > 1:
            draw.line(pts, fill=("royalblue", "darkorange")[k % 2], width=2)
        else:
            draw.ellipse([pts[0][0] - 2, pts[0][1] - 2, pts[0][0] + 2, pts[0][1] + 2], fill="royalblue")
    draw.text((pad, H - 25), f"step {x0} .. {x1}", fill="black")
    img.save(out_png)
