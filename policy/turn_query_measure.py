"""The turn locator's error, measured on recorded episodes (in `sudd pretrain --turn-locator`'s checks, which
`sudd export --turn-locator` records in the manifest's turn_query); the query itself is policy/turn_query.py.

On every verified episode of the family, the locator is asked the command about the recorded frames at the start
and half way to the collector's first close, as the runtime asks it on the way to a grasp, and the turn it says
is compared with the one the collector made from that frame on: its TCP's yaw at the close minus the yaw at the
frame, wrapped to the footprint's period. The collector turns early, so half way little turn is left; the policy,
which does not turn, leaves the whole turn to the locator, as at the start (`turn_deg_start_*`). Beside it the
error of not turning at all (the policy's own habit, policy/EXPERIMENTS.md, "The wrist turn") and how many answers
were sure enough to act on (policy.turn_query).
"""

from __future__ import annotations

import numpy as np
import torch

from policy.goal_locator import TURN_COLUMNS
from policy.grasp_axis import turn_of, wrap, yaw_of
from policy.instruction import embed_instructions


def recorded_turn(actions: np.ndarray, proprio: np.ndarray, period: float, at: int = 0) -> float | None:
    """The collector's wrist turn [rad] from step `at` to its first close, wrapped to [-period/2, period/2); None
    for an episode that never closes. actions (T, 10), proprio (T, >= 9): the recorded columns."""
    close = first_close(actions)
    if close is None:
        return None
    return wrap(float(yaw_of(actions[close, 3:9]) - yaw_of(proprio[at, 3:9])), period)


def first_close(actions: np.ndarray) -> int | None:
    """The step of the first close in recorded actions (T, 10); None where the gripper never closes."""
    shut = np.flatnonzero(np.asarray(actions)[:, -1] > 0.5)
    return int(shut[0]) if len(shut) else None


WAY = (0.0, 0.5)  # how far along the way to the first close the frames asked about are


@torch.no_grad()
def measure_turn(locator, data, family: str, period: float, embedder=None, episodes: int = 150) -> dict:
    """{episodes, answers, turn_deg_median, turn_deg_p75, turn_deg_start_median, turn_deg_start_p75,
    no_turn_deg_median, sure_share, period_deg} of a turn locator on up to `episodes` verified `family` episodes of
    `data` (module doc); a ValueError where none has a close late enough to ask before."""
    from datagen.store import Dataset
    from policy.goal_locator import LocatorGraph
    from policy.turn_query import MIN_NORM

    if embedder is None:
        from policy.text import default_embedder

        embedder = default_embedder()
    store, cfg = Dataset(data), locator.cfg
    graph = LocatorGraph(locator.eval())
    errors, still, norms, start, used = [], [], [], [], 0
    for row in store.episodes():
        if used >= episodes:
            break
        meta = store.meta(int(row["index"]))
        if meta.get("task") != family or not meta.get("success"):
            continue
        w = store.window(int(row["index"]), fields=("action", "proprio", *(f"{c}_rgb" for c in cfg.cameras)))
        close = first_close(w["action"])
        if close is None or close < 4:
            continue
        used += 1
        text = torch.from_numpy(embed_instructions(embedder, [meta["instruction"]], cfg.text_goal))
        for way in WAY:
            t = int(way * close)
            window = np.clip(np.arange(t - cfg.obs_horizon + 1, t + 1), 0, None)
            frames = [torch.from_numpy(w[f"{c}_rgb"][window][None]) for c in cfg.cameras]
            label = graph(*frames, text)[0, TURN_COLUMNS].numpy()
            truth = recorded_turn(w["action"], w["proprio"], period, at=t)
            errors.append(abs(wrap(turn_of(label, period) - truth, period)))
            if t == 0:
                start.append(errors[-1])
            still.append(abs(truth))
            norms.append(float(np.linalg.norm(label)))
    if not errors:
        raise ValueError(f"{data}: no verified {family} episode that closes the gripper 4 steps or more in, to "
                         f"measure the turn locator on; record some (sudd datagen --task {family})")
    deg = lambda e, q: round(float(np.degrees(np.percentile(e, q))), 1)  # noqa: E731
    return {"episodes": used, "answers": len(errors), "period_deg": round(float(np.degrees(period)), 1),
            "turn_deg_median": deg(errors, 50), "turn_deg_p75": deg(errors, 75), "no_turn_deg_median": deg(still, 50),
            "turn_deg_start_median": deg(start, 50), "turn_deg_start_p75": deg(start, 75),
            "sure_share": round(float(np.mean(np.asarray(norms) >= MIN_NORM)), 3)}


def turn_query_table(run_dir, policy_cfg, tasks) -> tuple[dict, torch.nn.Module]:
    """(the manifest's turn_query table, the locator) for `sudd export --turn-locator RUN`: the run's family and
    period, and its last check on its --data (`sudd pretrain --turn-locator`); refused where the policy was not
    trained on that family."""
    import json
    from pathlib import Path

    from policy.goal_locator import load_locator
    from policy.turn_query import MIN_NORM

    locator, record = load_locator(run_dir, policy_cfg, "turn")
    pre = json.loads((Path(run_dir) / "dataset.json").read_text())["pretrain"]
    summary = json.loads((Path(run_dir) / "summary.json").read_text())
    families = sorted({f.partition("/")[0] for f in pre.get("families", [])})
    missing = [f for f in families if f not in tasks]
    if not families or missing:
        raise ValueError(f"--turn-locator {run_dir}: taught on {families or 'no family'}, which the policy was not "
                         f"trained on ({', '.join(tasks)})")
    return {"families": families, "period_deg": float(pre["period_deg"]), "min_norm": MIN_NORM,
            "measured": {"data": str(pre.get("data", "")), **(summary.get("validation") or {})},
            "locator_from": {"run": str(run_dir), **record}}, locator
