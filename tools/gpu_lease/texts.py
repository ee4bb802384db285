"""Embed every instruction and subtask text of seeds [FIRST, LAST) of each task before the data exists.

usage: python tools/gpu_lease/texts.py FIRST LAST OUT.npz [--task T ...] [--holdout-color purple]
Builds each episode's scene (no physics) and runs the offline planner, as `sudd datagen` does, so the
texts are exactly those the data will hold; embeds them, and their goal clauses (policy.instruction: what a
`text_goal` policy reads in its second slot), with the frozen MiniLM (policy.text).
"""
import argparse
from multiprocessing import Pool

import numpy as np


def texts_of(job: tuple[str, int, tuple[str, ...]]) -> list[str]:
    from datagen.episode import DatagenConfig
    from datagen.plan import describe
    from datagen.planner import make_planner
    from sim.build import build_episode
    from sim.config import load_config

    task, seed, colors = job
    cfg = load_config(DatagenConfig, {"dr": "heavy", "holdout_colors": list(colors)})
    ep = build_episode(task, seed, cfg.dr, cfg.fidelity, holdout=cfg.holdout())
    plan = make_planner(cfg.planner).plan(ep.instruction, describe(ep.instance))
    return [ep.instruction] + [s.text for s in plan.subtasks]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("first", type=int)
    p.add_argument("last", type=int)
    p.add_argument("out")
    p.add_argument("--task", action="append", help="default: pick_place")
    p.add_argument("--holdout-color", action="append", default=["purple"])
    a = p.parse_args()
    with Pool(2) as pool:
        jobs = [(t, s, tuple(a.holdout_color)) for t in a.task or ["pick_place"] for s in range(a.first, a.last)]
        rows = pool.map(texts_of, jobs, chunksize=20)
    from policy.instruction import goal_clause

    said = {t for r in rows for t in r}
    texts = sorted(said | {c for c in map(goal_clause, said) if c is not None})
    from policy.text import default_embedder

    np.savez(a.out, texts=np.array(texts), table=np.asarray(default_embedder()(texts), np.float32))
    print(f"{len(texts)} texts of seeds {a.first}-{a.last - 1} of {a.task or ['pick_place']} -> {a.out}")


if __name__ == "__main__":
    main()
