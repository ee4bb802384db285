"""Training curves from metrics.jsonl to a PNG: loss (log axis), learning rate and, when the run validates
(policy.validate), the loss and the grasp-point error on unseen vs training episodes.

Drawn with Pillow (a project dependency; matplotlib is not), so every run ends with the same picture on
every machine.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

COLORS = ("royalblue", "darkorange", "seagreen", "dimgray")  # the fourth: a reference line (constant guess)
Line = tuple[str, list[int], list[float]]  # label, steps, values


def read_metrics(path: str | Path) -> list[dict]:
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_metrics(metrics_path: str | Path, out_png: str | Path) -> Path | None:
    rows = read_metrics(metrics_path)
    train = [r for r in rows if "loss" in r]
    if not train:
        return None
    checks = [r for r in rows if "val_loss" in r]

    def line(label: str, rs: list[dict], key: str) -> Line:
        return label, [r["step"] for r in rs], [r[key] for r in rs]

    loss = [line("train", train, "loss")]
    if checks:
        loss += [line("unseen episodes", checks, "val_loss"), line("training episodes", checks, "fit_loss")]
    panels = [("loss", loss, True), ("lr", [line("lr", train, "lr")], False)]
    sampled = [r for r in checks if "val_chunk_cm" in r]  # rows written before it was logged have none
    if sampled:
        panels.append(("sampled chunk vs recorded [cm]", [line("unseen episodes", sampled, "val_chunk_cm"),
                                                          line("training episodes", sampled, "fit_chunk_cm")], False))
    grasp = [r for r in checks if "val_grasp_cm" in r]
    if grasp:
        lines = [line("unseen episodes", grasp, "val_grasp_cm"), line("training episodes", grasp, "fit_grasp_cm")]
        aiming = [r for r in grasp if "val_pregrasp_cm" in r]  # likewise for this one
        if aiming:
            lines.append(line("unseen, before the grasp", aiming, "val_pregrasp_cm"))
        placing = [r for r in grasp if "val_release_cm" in r]
        if placing:
            lines.append(line("unseen, release point while carrying", placing, "val_release_cm"))
        guessed = [r for r in grasp if "guess_grasp_cm" in r]  # rows written before it was logged have none
        if guessed:
            lines.append(line("constant guess", guessed, "guess_grasp_cm"))
        panels.append(("aux head: grasp (and release) point error [cm]", lines, False))
    goal = [r for r in rows if "goal_cm_median" in r]  # a goal locator's run (policy/goal_locator.py)
    if goal:
        panels.append(("goal query: release point error on unseen episodes [cm]",
                       [line("median", goal, "goal_cm_median"), line("p75", goal, "goal_cm_p75")], False))
    found = [r for r in rows if "object_grasp_cm_median" in r]  # an object locator's run
    if found:
        panels.append(("object locator: error on unseen episodes' first frames [cm]",
                       [line("object (grasp), median", found, "object_grasp_cm_median"),
                        line("drop (release), median", found, "object_release_cm_median"),
                        line("object (grasp), p75", found, "object_grasp_cm_p75")], False))
    _draw(panels, out_png)
    return Path(out_png)


def _draw(panels: list[tuple[str, list[Line], bool]], out_png: str | Path) -> None:
    from PIL import Image, ImageDraw

    W, pad, panel_h = 800, 50, 225
    H = panel_h * len(panels) + pad
    img = Image.new("RGB", (W, H), "white")
    draw = ImageDraw.Draw(img)
    all_steps = [s for _, lines, _ in panels for _, steps, _ in lines for s in steps]
    x0, x1 = min(all_steps), max(all_steps)
    x1 = x1 if x1 > x0 else x0 + 1
    for k, (name, lines, log) in enumerate(panels):
        top, bottom = k * panel_h + 20, (k + 1) * panel_h - 10
        tf = (lambda y: math.log10(max(y, 1e-12))) if log else (lambda y: y)
        ys_all = [tf(y) for _, _, ys in lines for y in ys]
        lo, hi = min(ys_all), max(ys_all)
        hi = hi if hi > lo else lo + 1e-12
        draw.rectangle([pad, top, W - 20, bottom], outline="gray")
        colors = [COLORS[j % len(COLORS)] if len(lines) > 1 else COLORS[k % 2] for j in range(len(lines))]
        # the legend: each series' name and last value in its own colour
        x = pad + 5
        for text, color in [(f"{name}{' (log axis)' if log else ''}, last:", "black")] + \
                [(f"{label} {ys[-1]:.4g}", c) for (label, _, ys), c in zip(lines, colors)]:
            draw.text((x, top + 3), text, fill=color)
            x += draw.textlength(text + "  ")
        for value, y in ((hi, top + 15), (lo, bottom - 10)):  # the y range, in the data's units
            draw.text((2, y - 5), f"{10 ** value if log else value:.3g}", fill="gray")
        for j, (_, steps, ys) in enumerate(lines):
            pts = [(pad + (s - x0) / (x1 - x0) * (W - 20 - pad), bottom - (tf(y) - lo) / (hi - lo) * (bottom - top - 15))
                   for s, y in zip(steps, ys)]
            color = colors[j]
            if len(pts) > 1:
                draw.line(pts, fill=color, width=2)
            if len(pts) <= 60:  # dots mark sparse series (validation rows), not the per-log-step curves
                for x, y in pts:
                    draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=color)
    draw.text((pad, H - 25), f"step {x0} .. {x1}", fill="black")
    img.save(out_png)
