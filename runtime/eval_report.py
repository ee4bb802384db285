"""Evaluation results: success rates with 95% confidence intervals, a markdown table and a bar chart (PNG).

Rows are (suite, task, who): `who` is "policy" (the bundle, closed loop) or "collector" (the data-collection
policy: planner + primitives + verify-and-retry, privileged state, on the same seeds). The interval is
Wilson's score interval: unlike the normal approximation it stays inside [0, 1] and is honest at 0/N and N/N,
which small evaluations hit often.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from statistics import median
from pathlib import Path

from sim.tasks.drawer import OPEN_FRACTION

Z95 = 1.959963984540054
SUITES = {
    "seen": "held-out seeds, training objects and phrasings",
    "heldout": "held-out seeds, target of a held-out colour/shape",
    "heldout_shape": "held-out seeds, target of a shape no training scene held (a ball)",
    "paraphrase": "held-out seeds, an unseen phrasing of the command",
}


def _suite_rank(suite: str) -> int:
    """Suites in SUITES order, unknown ones last."""
    return list(SUITES).index(suite) if suite in SUITES else len(SUITES)


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """95% Wilson score interval of a binomial proportion; (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def summarise(records: list[dict]) -> list[dict]:
    """Per (suite, task, who): n, successes, rate, 95% CI; median time to success, inference p50, and the
    failed episodes counted by failure class and by how they ended."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        groups[(r["suite"], r["task"], r["who"])].append(r)
    rows = []
    for (suite, task, who), rs in sorted(groups.items(), key=lambda kv: (_suite_rank(kv[0][0]), kv[0][1:])):
        k = sum(bool(r["success"]) for r in rs)
        lo, hi = wilson(k, len(rs))
        times = sorted(r["sim_seconds"] for r in rs if r["success"] and r.get("sim_seconds") is not None)
        infer = sorted(r["inference_ms"]["p50"] for r in rs if isinstance(r.get("inference_ms"), dict))
        failures = Counter(r["failure"] for r in rs if r.get("failure"))
        ends = Counter(r["end"] for r in rs if not r["success"] and r.get("end"))
        near = sorted(r["closest_cm"] for r in rs if r.get("failure") == "no_grasp" and r.get("closest_cm") is not None)
        hits = [r["stop_speed_cm_s"] for r in rs if r.get("stop_speed_cm_s") is not None]
        holding = sum(bool(r.get("stop_fingers_closed")) for r in rs if r.get("stop_speed_cm_s") is not None)
        turned = [[abs(c["yaw_off_deg"]) for c in r.get("closes", ()) if c.get("yaw_off_deg") is not None]
                  for r in rs if r.get("failure") == "no_grasp"]
        yaw = sorted(median(t) for t in turned if t)
        ok, tnp = [r for r in rs if r["success"]], [r for r in rs if r.get("failure") == "target_not_placed"]
        drawer = [r["drawer_max"] for r in rs if not r["success"] and r.get("drawer_max") is not None]
        # (family run as, succeeded) of the commands run as another; records before runs_as ran as their own
        other = Counter((r["runs_as"] or "none", bool(r["success"])) for r in rs if r.get("runs_as", task) != task)
        rows.append({"suite": suite, "task": task, "who": who, "n": len(rs), "successes": k, "rate": k / len(rs),
                     "ci95": [lo, hi], "median_success_s": times[len(times) // 2] if times else None,
                     "inference_p50_ms": infer[len(infer) // 2] if infer else None,
                     "failures": dict(failures), "ends": dict(ends),
                     "no_grasp_closest_cm": near[len(near) // 2] if near else None,
                     "stop_speed_cm_s": median(hits) if hits else None,
                     "stops_fingers_closed": holding,
                     "no_grasp_close_yaw_off_deg": yaw[len(yaw) // 2] if yaw else None,
                     "release_off_cm": {"success": _last_release_cm(ok), "target_not_placed": _last_release_cm(tnp)},
                     "release_aim_off_cm": {"success": _last_release_cm(ok, "aim_"),
                                            "target_not_placed": _last_release_cm(tnp, "aim_")},
                     "release_in_hand_cm": {"success": _last_release_in_hand_cm(ok),
                                            "target_not_placed": _last_release_in_hand_cm(tnp)},
                     "release_over_cm": {"success": _last_release_over_cm(ok),
                                         "target_not_placed": _last_release_over_cm(tnp)},
                     "release_outside_cm": {"success": _last_release_outside_cm(ok),
                                            "target_not_placed": _last_release_outside_cm(tnp)},
                     "target_ends": dict(Counter(r["target_end"] for r in rs if r.get("target_end"))),
                     "failed_drawer_opened": sum(f >= OPEN_FRACTION for f in drawer) if drawer else None,
                     "runs_as_other": {f: [other[f, True] + other[f, False], other[f, True]]
                                       for f in sorted({f for f, _ in other})}})
    return rows


def _median_at_last_let_go(records: list[dict], measure) -> float | None:
    """Median of `measure(release)` over the records that let go of the named object, each at its last let-go;
    None where none did or `measure` gave None for every one (a field not recorded)."""
    values = [measure(r["releases"][-1]) for r in records if r.get("releases")]
    values = [v for v in values if v is not None]
    return median(values) if values else None


def _last_release_cm(records: list[dict], prefix: str = "") -> float | None:
    """How far (horizontally) from the goal bin's centre the object last left the fingers (prefix "aim_": where
    the followed chunk aimed the TCP then)."""
    return _median_at_last_let_go(records, lambda x: None if x.get(f"{prefix}dx_cm") is None
                                  else math.hypot(x[f"{prefix}dx_cm"], x[f"{prefix}dy_cm"]))


def _last_release_in_hand_cm(records: list[dict]) -> float | None:
    """How far (horizontally) the object sat from the TCP in the fingers as it last left them (where it left them
    minus where the TCP was). Why: a block let go off its goal was either aimed off or held off centre, and only
    the first is the aim's fault."""
    return _median_at_last_let_go(records, lambda x: None if x.get("dx_cm") is None or x.get("tcp_dx_cm") is None
                                  else math.hypot(x["dx_cm"] - x["tcp_dx_cm"], x["dy_cm"] - x["tcp_dy_cm"]))


def _last_release_over_cm(records: list[dict]) -> float | None:
    """Stack: how high over resting on the other block the named block last left the fingers (None for a task
    with a bin, which records none)."""
    return _median_at_last_let_go(records, lambda x: x.get("over_cm"))


def _last_release_outside_cm(records: list[dict]) -> float | None:
    """The drawer: how far beyond the edges of its inside the named object last left the fingers (0 over it; None
    for a task without the drawer)."""
    return _median_at_last_let_go(records, lambda x: x.get("outside_cm"))


def markdown_table(rows: list[dict]) -> str:
    """One line per (suite, task): the policy's and the collector's success side by side."""
    by = {(r["suite"], r["task"], r["who"]): r for r in rows}
    keys = sorted({(r["suite"], r["task"]) for r in rows}, key=lambda k: (_suite_rank(k[0]), k[1]))
    lines = ["| suite | task | policy success [95% CI] | data collector [95% CI] | policy median time to success |",
             "|---|---|---|---|---|"]
    for suite, task in keys:
        pol, col = by.get((suite, task, "policy")), by.get((suite, task, "collector"))
        t = pol["median_success_s"] if pol else None
        lines.append(f"| {suite} | {task} | {_cell(pol)} | {_cell(col)} | {'-' if t is None else f'{t:.1f} s'} |")
    return "\n".join(lines)


def failure_table(rows: list[dict]) -> str:
    """Why the policy's failed episodes failed (runtime.eval_progress) and how they ended; "" if none failed."""
    from runtime.eval_progress import FAILURES, TARGET_ENDS

    pol = [r for r in rows if r["who"] == "policy" and r["successes"] < r["n"]]
    if not pol:
        return ""
    ends = sorted({e for r in pol for e in r.get("ends", {})})
    lines = ["| suite | task | failed | " + " | ".join(FAILURES + tuple(f"ended: {e}" for e in ends))
             + " | force stops: TCP speed at the stop (median); how many with the fingers closed "
             "| no_grasp: median closest approach | no_grasp: yaw off at a close (median) "
             "| target_not_placed: the object ended "
             "| target_not_placed: let go off the goal's centre (median; where the chunk aimed the TCP; how far off "
             "the TCP the fingers held it; stack: how high over resting on the other; drawer: how far outside its "
             "inside) "
             f"| drawer opened (>= {OPEN_FRACTION:.0%} of its travel) |",
             "|---|---|---|" + "---|" * (len(FAILURES) + len(ends) + 6)]
    for r in sorted(pol, key=lambda r: (_suite_rank(r["suite"]), r["task"])):
        near, hit = r.get("no_grasp_closest_cm"), r.get("stop_speed_cm_s")
        cells = [str(r.get("failures", {}).get(f, 0)) for f in FAILURES] + [str(r["ends"].get(e, 0)) for e in ends]
        cells.append("-" if hit is None else f"{hit:.1f} cm/s; {r.get('stops_fingers_closed', 0)} closed")
        cells.append("-" if near is None else f"{near:.1f} cm")
        yaw = r.get("no_grasp_close_yaw_off_deg")
        cells.append("-" if yaw is None else f"{yaw:.0f} deg")
        where = r.get("target_ends", {})
        cells.append(", ".join(f"{e} {where[e]}" for e in TARGET_ENDS if where.get(e)) or "-")
        off = (r.get("release_off_cm") or {}).get("target_not_placed")
        aim = (r.get("release_aim_off_cm") or {}).get("target_not_placed")
        over = (r.get("release_over_cm") or {}).get("target_not_placed")
        outside = (r.get("release_outside_cm") or {}).get("target_not_placed")
        hand = (r.get("release_in_hand_cm") or {}).get("target_not_placed")
        how = "; ".join(([] if aim is None else [f"aimed {aim:.1f} cm"])
                        + ([] if hand is None else [f"held {hand:.1f} cm off"]))
        cells.append("-" if off is None else f"{off:.1f} cm" + (f" ({how})" if how else "")
                     + ("" if over is None else f", {over:.1f} cm over its rest")
                     + ("" if outside is None else f", {outside:.1f} cm outside the drawer"))
        opened = r.get("failed_drawer_opened")
        cells.append("-" if opened is None else str(opened))
        lines.append(f"| {r['suite']} | {r['task']} | {r['n'] - r['successes']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def routing_note(rows: list[dict]) -> str:
    """A sentence naming the episodes whose command the policy node would run as another family
    (runtime.command_family), with how many of them succeeded; "" where every command ran as its own."""
    parts = [f"{r['suite']} {r['task']} as {f}: {n} ({k} succeeded)"
             for r in rows if r["who"] == "policy" for f, (n, k) in r.get("runs_as_other", {}).items()]
    if not parts:
        return ""
    return ("Commands run as another family, judged as the policy node judges them (its closest trained "
            "instruction's; runtime/command_family.py): " + "; ".join(parts) + ".")


def _cell(r: dict | None) -> str:
    if r is None:
        return "-"
    lo, hi = r["ci95"]
    return f"{r['successes']}/{r['n']} = {100 * r['rate']:.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]"


def plot(rows: list[dict], out_png: str | Path, title: str = "closed-loop success (95% Wilson CI)") -> Path:
    """Grouped bars (policy, collector) per (suite, task) with CI whiskers; Pillow only."""
    from PIL import Image, ImageDraw

    groups = sorted({(r["suite"], r["task"]) for r in rows}, key=lambda k: (_suite_rank(k[0]), k[1]))
    by = {(r["suite"], r["task"], r["who"]): r for r in rows}
    colors = {"policy": (52, 101, 164), "collector": (170, 170, 170)}
    gw, bw, left, top, h = 150, 50, 60, 40, 260
    W, H = max(left + gw * max(1, len(groups)) + 20, left + 340), top + h + 70
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)
    d.text((left, 10), title, fill="black")
    for k in range(0, 101, 20):
        y = top + h - h * k / 100
        d.line([(left - 5, y), (W - 10, y)], fill=(225, 225, 225))
        d.text((10, y - 6), f"{k}%", fill="black")
    for g, (suite, task) in enumerate(groups):
        x0 = left + g * gw + 20
        for j, who in enumerate(("policy", "collector")):
            r = by.get((suite, task, who))
            if r is None:
                continue
            x = x0 + j * (bw + 6)
            y = top + h - h * r["rate"]
            d.rectangle([x, y, x + bw, top + h], fill=colors[who])
            lo, hi = (top + h - h * v for v in r["ci95"])
            cx = x + bw / 2
            d.line([(cx, lo), (cx, hi)], fill="black", width=2)
            d.line([(cx - 8, lo), (cx + 8, lo)], fill="black", width=2)
            d.line([(cx - 8, hi), (cx + 8, hi)], fill="black", width=2)
            d.text((x + 4, max(top, y - 14)), f"{100 * r['rate']:.0f}%", fill="black")
        d.text((x0, top + h + 8), task, fill="black")
        d.text((x0, top + h + 22), suite, fill=(90, 90, 90))
    ly = H - 22
    for j, (who, c) in enumerate(colors.items()):
        d.rectangle([left + j * 160, ly, left + j * 160 + 14, ly + 12], fill=c)
        d.text((left + j * 160 + 20, ly), "policy (bundle)" if who == "policy" else "data collector", fill="black")
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out)
    return out
