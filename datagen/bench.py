"""`sudd bench datagen`: successful episodes per core-hour and the data-collection success rate per task.

One process on one core, the production settings (heavy DR, fast fidelity, 2 cameras at 128x128, 10 Hz),
seeds 10_000.. so they never coincide with a dataset's default seeds. Wall time covers everything an
episode costs: building and randomizing the scene, planning, motion planning, physics, rendering, checks.
"""

from __future__ import annotations

import statistics
import time

from datagen.episode import DatagenConfig, run_episode
from sim.tasks import task_names

BENCH_SEED = 10_000


def run_datagen_bench(quick: bool = False, episodes: int | None = None) -> dict:
    n = episodes or (2 if quick else 10)
    cfg = DatagenConfig()
    per_task = {}
    for task in task_names():
        walls, successes, retries, agree = [], 0, [], 0
        for seed in range(BENCH_SEED, BENCH_SEED + n):
            t0 = time.perf_counter()
            data = run_episode(task, seed, cfg)
            walls.append(time.perf_counter() - t0)
            successes += data.meta["success"]
            retries.append(data.meta["retries"])
            agree += data.meta["success"] == data.meta["check_success"]
        total = sum(walls)
        per_task[task] = {
            "episodes": n,
            "success_rate": successes / n,
            "successful_episodes_per_core_hour": successes / total * 3600.0,
            "episodes_per_core_hour": n / total * 3600.0,
            "median_episode_s": statistics.median(walls),
            "mean_retries": sum(retries) / n,
            "check_agrees_with_ground_truth": agree / n,
        }
    return {"quick": quick, "config": {"dr": cfg.dr, "fidelity": cfg.fidelity, "image_size": list(cfg.image_size),
                                       "cameras": 2, "hz": 10, "max_retries": cfg.max_retries},
            "per_task": per_task,
            "target": {"pick_place_successful_episodes_per_core_hour": 300}}


def format_table(result: dict) -> str:
    lines = [f"datagen bench{' (quick)' if result['quick'] else ''}: one core, DR {result['config']['dr']}, "
             f"2 cameras {result['config']['image_size']} at 10 Hz", "",
             f"{'task':14} {'n':>4} {'success':>8} {'ok eps/core-h':>14} {'eps/core-h':>11} {'median s':>9} "
             f"{'retries':>8} {'check=truth':>11}"]
    for task, r in result["per_task"].items():
        lines.append(f"{task:14} {r['episodes']:4d} {r['success_rate']:8.0%} {r['successful_episodes_per_core_hour']:14.0f} "
                     f"{r['episodes_per_core_hour']:11.0f} {r['median_episode_s']:9.2f} {r['mean_retries']:8.2f} "
                     f"{r['check_agrees_with_ground_truth']:11.0%}")
    return "\n".join(lines)
