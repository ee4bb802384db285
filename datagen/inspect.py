"""Look at a generated dataset: per-task statistics, and a contact sheet of one episode.

The statistics are the ones that tell whether a generation run is healthy: success rate per task, how long
episodes run, how often subtasks had to be retried, and how often the plan's check snippets agree with the
simulator's ground-truth predicate (low agreement means the checks, hence the labels, cannot be trusted).
The contact sheet shows what the policy will see: both cameras over time with the subtask being executed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from datagen.schema import CAMERAS, CONTROL_HZ, PERTURBED, SCHEMA_VERSION
from datagen.store import Dataset

_BG, _FG, _DIM = (24, 24, 28), (235, 235, 235), (150, 150, 160)
_OK, _BAD = (70, 190, 90), (220, 70, 60)
_PALETTE = [(66, 135, 245), (245, 166, 35), (80, 200, 120), (200, 90, 220), (240, 90, 90), (60, 200, 200),
            (230, 220, 60), (170, 120, 80)]
_GAP = 6


def _rate(num: int, den: int) -> float | None:
    return round(num / den, 4) if den else None


def dataset_info(root: str | Path) -> dict:
    """Counts and per-task statistics of the committed episodes under ROOT (metadata only, fast)."""
    ds = Dataset(root)
    rows = ds.episodes()
    tasks: dict[str, dict] = {}
    for task in sorted({r["task"] for r in rows}):
        mine = [r for r in rows if r["task"] == task]
        checked = [r for r in mine if r.get("check_success") is not None]
        retries = [r["retries"] for r in mine if isinstance(r.get("retries"), (int, float))]
        tasks[task] = {
            "episodes": len(mine),
            "success_rate": _rate(sum(bool(r.get("success")) for r in mine), len(mine)),
            "mean_length": round(float(np.mean([r["length"] for r in mine])), 1),
            "mean_retries": round(float(np.mean(retries)), 2) if retries else None,
            "check_agreement": _rate(sum(bool(r["check_success"]) == bool(r.get("success")) for r in checked),
                                     len(checked)),
        }
    checked = [r for r in rows if r.get("check_success") is not None]
    return {
        "path": str(root), "schema_version": SCHEMA_VERSION, "shards": sorted(ds.shards),
        "skipped_shards": ds.skipped, "episodes": len(rows), "steps": ds.num_steps,
        "hours_of_data": round(ds.num_steps / CONTROL_HZ / 3600, 3),
        "success_rate": _rate(sum(bool(r.get("success")) for r in rows), len(rows)),
        "check_agreement": _rate(sum(bool(r["check_success"]) == bool(r.get("success")) for r in checked),
                                 len(checked)),
        "content_hash": ds.content_hash(), "tasks": tasks,
    }


def format_info(info: dict) -> str:
    """The info dict as a text table, one row per task and a total."""
    def pct(x):
        return "-" if x is None else f"{100 * x:.0f}%"

    def num(x):
        return "-" if x is None else f"{x:g}"

    head = ("task", "episodes", "success", "mean len", "mean retries", "check agrees")
    body = [(t, str(s["episodes"]), pct(s["success_rate"]), num(s["mean_length"]), num(s["mean_retries"]),
             pct(s["check_agreement"])) for t, s in info["tasks"].items()]
    total = ("TOTAL", str(info["episodes"]), pct(info["success_rate"]), "", "", pct(info["check_agreement"]))
    widths = [max(len(r[i]) for r in [head, *body, total]) for i in range(len(head))]
    line = lambda r: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
    out = [f"dataset {info['path']}: {info['episodes']} episodes, {info['steps']} steps "
           f"({info['hours_of_data']} h at {CONTROL_HZ:g} Hz) in {len(info['shards'])} shard(s)", "",
           line(head), line(tuple("-" * w for w in widths)), *map(line, body), line(total), "",
           f"content hash {info['content_hash']}"]
    for name, reason in info["skipped_shards"].items():
        out.append(f"SKIPPED shard {name}: {reason}")
    return "\n".join(out)


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has only the fixed bitmap font
        return ImageFont.load_default()


def _wrap(draw: ImageDraw.ImageDraw, text: str, font, width: int, max_lines: int = 3) -> list[str]:
    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cur and draw.textlength(trial, font=font) > width:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    lines.append(cur)
    if len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] = lines[-1][:max(0, len(lines[-1]) - 1)] + "…"
    return lines


def contact_sheet(root: str | Path, episode_index: int, out_png: str | Path, samples: int = 10) -> Path:
    """Write a PNG of episode EPISODE_INDEX: both cameras at `samples` evenly spaced times, each column
    captioned with the time and the running subtask's language label, under a header with the root
    instruction, task, seed and success, above a timeline of the subtasks."""
    ds = Dataset(root)
    if not 0 <= episode_index < len(ds):
        raise IndexError(f"episode {episode_index} out of range: the dataset has {len(ds)} episodes (0..{len(ds) - 1})")
    ep, meta = ds.episode(episode_index), ds.meta(episode_index)
    T = len(ep)
    steps = np.unique(np.linspace(0, T - 1, min(samples, T)).round().astype(int))
    h, w = ep.images[CAMERAS[0]].shape[1:3]
    scale = max(1, int(np.ceil(160 / w)))
    tw, th = w * scale, h * scale
    labels = list(meta.get("subtasks") or [])
    f_title, f_text, f_small = _font(22), _font(15), _font(13)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    label_col = 70
    cap_lines = max(len(_wrap(probe, _subtask_text(labels, int(ep.subtask[s])), f_small, tw)) for s in steps)
    header_h, cap_top, cap_bottom = 64, 22, 8 + 16 * cap_lines
    legend = len(labels) + len(np.unique(ep.subtask[ep.subtask < 0]))
    timeline_h = 36 + 18 * ((legend + 1) // 2)
    width = label_col + len(steps) * (tw + _GAP) + _GAP
    height = header_h + cap_top + len(CAMERAS) * (th + _GAP) + cap_bottom + timeline_h
    sheet = Image.new("RGB", (width, height), _BG)
    d = ImageDraw.Draw(sheet)

    d.text((_GAP + 4, 8), _wrap(d, f"\u201c{meta.get('instruction') or '(no instruction)'}\u201d", f_title,
                                width - 260, 1)[0], fill=_FG, font=f_title)
    ok = bool(meta.get("success"))
    badge = "SUCCESS" if ok else "FAILED"
    bw = d.textlength(badge, font=f_title) + 20
    d.rounded_rectangle((width - bw - _GAP, 6, width - _GAP, 36), 6, fill=_OK if ok else _BAD)
    d.text((width - bw - _GAP + 10, 9), badge, fill=(255, 255, 255), font=f_title)
    check = meta.get("check_success")
    sub = (f"task {meta.get('task')}  |  seed {meta.get('seed')}  |  episode {episode_index} (shard "
           f"{ds.episodes()[episode_index]['shard']})  |  {T} steps, {float(ep.time[-1] - ep.time[0]):.1f} s  |  "
           f"check snippets: {'-' if check is None else ('pass' if check else 'fail')}  |  "
           f"retries {meta.get('retries')}  |  planner {meta.get('planner')}")
    d.text((_GAP + 4, 40), sub, fill=_DIM, font=f_text)

    y_img = header_h + cap_top
    for r, cam in enumerate(CAMERAS):
        d.text((_GAP + 4, y_img + r * (th + _GAP) + th // 2 - 8), cam, fill=_FG, font=f_text)
    for c, s in enumerate(steps):
        x = label_col + c * (tw + _GAP)
        d.text((x, header_h + 2), f"t={float(ep.time[s]):.1f}s  step {s}", fill=_FG, font=f_small)
        for r, cam in enumerate(CAMERAS):
            img = Image.fromarray(ep.images[cam][s]).resize((tw, th), Image.NEAREST)
            sheet.paste(img, (x, y_img + r * (th + _GAP)))
        k = int(ep.subtask[s])
        y = y_img + len(CAMERAS) * (th + _GAP)
        d.rectangle((x, y, x + tw - 1, y + 3), fill=_color(k))
        for j, line in enumerate(_wrap(d, _subtask_text(labels, k), f_small, tw)):
            d.text((x, y + 6 + 16 * j), line, fill=_FG, font=f_small)

    _timeline(d, ep, steps, labels, label_col, height - timeline_h + 8, width - label_col - _GAP, f_small)
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out


def _subtask_text(labels: list[str], k: int) -> str:
    if k == PERTURBED:
        return "(injected failure)"
    if k < 0:
        return "(recovering)"
    return f"{k + 1}. {labels[k]}" if k < len(labels) else f"subtask {k}"


def _color(k: int) -> tuple:
    if k == PERTURBED:
        return (200, 60, 60)
    return (110, 110, 110) if k < 0 else _PALETTE[k % len(_PALETTE)]


def _timeline(d, ep, steps, labels, x0: int, y0: int, width: int, font) -> None:
    """A bar over the whole episode coloured by subtask, ticks at the sampled steps, and a legend."""
    T = len(ep)
    d.text((_GAP + 4, y0 - 2), "subtask", fill=_DIM, font=font)
    for t in range(T):
        a, b = x0 + width * t // T, x0 + width * (t + 1) // T
        d.rectangle((a, y0, max(a, b - 1), y0 + 12), fill=_color(int(ep.subtask[t])))
    for s in steps:
        x = x0 + int(width * (s + 0.5) / T)
        d.line((x, y0 - 4, x, y0 + 15), fill=_FG, width=1)
    entries = [(k, _subtask_text(labels, k)) for k in range(len(labels))]
    entries += [(k, _subtask_text(labels, k)) for k in (-1, PERTURBED) if np.any(ep.subtask == k)]
    col_w = width // 2
    for n, (k, text) in enumerate(entries):
        x, y = x0 + (n % 2) * col_w, y0 + 22 + 18 * (n // 2)
        d.rectangle((x, y + 3, x + 10, y + 13), fill=_color(k))
        d.text((x + 16, y), _wrap(d, text, font, col_w - 24, 1)[0], fill=_FG, font=font)
