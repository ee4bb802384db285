"""`sudd datagen`: generate labelled episodes from language with verify-and-retry, in parallel, resumably.

Each episode is (task, seed): the planner splits the task's instruction into subtasks, sampling-based
primitives (grasp/place samplers, OMPL motion planning) execute them, sandboxed check snippets verify each
one, and failures are recovered and retried. Episodes land in a sharded zarr store; re-running the same
command resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    gen = sub.add_parser(
        "datagen", help="generate labelled episodes (planner + primitives + verify-and-retry)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  sudd datagen --task pick_place --episodes 100 --out out/data --workers 2\n"
               "  sudd datagen --task all --episodes 50 --out out/data --dr heavy\n"
               "  sudd datagen --task all --episodes 500 --out /shared/data --ray auto\n"
               "  sudd datagen --task drawer_open --seeds 100003,100015,700000-700049 --out out/again\n"
               "  SUDD_LLM_API_KEY=... sudd datagen --task stack --episodes 20 --out out/llm \\\n"
               "      --planner llm --llm-url http://localhost:8000/v1 --llm-model my-model")
    gen.add_argument("--task", action="append", required=True,
                     help="task family (repeatable), or 'all' (see `sudd sim tasks`)")
    gen.add_argument("--episodes", type=int, help="episodes per task (or give --seeds)")
    gen.add_argument("--out", type=Path, required=True, help="dataset directory (created; resumed if present)")
    gen.add_argument("--workers", type=int, default=1, help="worker processes (one shard each; default 1)")
    gen.add_argument("--seed-offset", type=int, default=None, help="first seed; seeds are OFFSET..OFFSET+N-1 "
                     "(default 0)")
    gen.add_argument("--seeds", default=None, metavar="LIST|FILE",
                     help="exactly these seeds for every task instead of --episodes/--seed-offset: e.g. "
                          "100003,100015,700000-700199, or a file of them (one or more per line, # comments); "
                          "to re-run an eval's failures with the collector, or a chosen part of the randomization")
    gen.add_argument("--ray", default=None, metavar="auto|ADDRESS|local",
                     help="run the workers on a Ray cluster instead of local processes")
    gen.add_argument("--dr", default="heavy", help="DR preset off|light|heavy or a TOML file (default heavy)")
    gen.add_argument("--fidelity", default="fast", choices=("full", "fast"), help="rendering fidelity")
    gen.add_argument("--max-retries", type=int, default=4, help="retries per subtask (default 4)")
    gen.add_argument("--perturb", type=float, default=0.0, metavar="P",
                     help="probability that a place is disturbed (object dropped), so the data holds recoveries")
    gen.add_argument("--perturb-grasp", type=float, default=0.0, metavar="P",
                     help="probability that a pick's gripper closes early, above the object (a missed grasp), "
                          "so the data holds regrasps")
    gen.add_argument("--path-noise-cm", type=float, default=0.0, metavar="CM",
                     help="DART noise injection: push the executed path off the plan while the arm moves by a smooth "
                          "offset of this std (cm per axis) while the actions stay the plan's, so the policy "
                          "learns to steer back to it (0-5; default 0: off)")
    gen.add_argument("--grasp-noise-cm", type=float, default=0.0, metavar="CM",
                     help="close each pick's grasp at a random horizontal offset of this std (cm per axis) from the "
                          "planned grasp while the actions stay the plan's, so the policy learns to close when "
                          "near, not only exactly on the plan (0-3; default 0: off)")
    gen.add_argument("--handle-grasp", default="top", choices=("top", "front"),
                     help="how a drawer's handle is grasped: from above (default) or from the front, level, the "
                          "fingers closing above and below the bar")
    gen.add_argument("--gripper", default="driver", choices=("driver", "servo"),
                     help="driver (default): the fingers move as the 2F-85's driver and the runtime's twin move them, "
                          "at --gripper-speed and --gripper-force, each grasp and release held until they stop; "
                          "servo: the collector before 2026-12-07, fingers shut in 0.1 s with ~5x the squeeze "
                          "(to remake older datasets)")
    gen.add_argument("--gripper-speed", type=float, default=0.08, metavar="M_S",
                     help="finger speed with --gripper driver (0.02-0.15 m/s; default 0.08, the runtime's)")
    gen.add_argument("--gripper-force", type=float, default=40.0, metavar="N",
                     help="grip force with --gripper driver (20-235 N; default 40, the runtime's)")
    gen.add_argument("--holdout-color", action="append", default=[], metavar="COLOR",
                     help="never use this object colour (repeatable), so `sudd eval --heldout` can test it")
    gen.add_argument("--holdout-shape", action="append", default=[], metavar="SHAPE",
                     help="never use this object shape (repeatable)")
    gen.add_argument("--label", default="ground_truth", choices=("ground_truth", "check"),
                     help="success label for training: the task predicate or the plan's own checks")
    gen.add_argument("--planner", default="offline", choices=("offline", "llm"))
    gen.add_argument("--llm-url", default="", help="OpenAI-compatible endpoint (key from $SUDD_LLM_API_KEY)")
    gen.add_argument("--llm-model", default="", help="model name at that endpoint")
    gen.add_argument("--json", action="store_true", help="print the run summary as JSON")
    gen.set_defaults(func=_generate)


def _generate(args) -> int:
    from datagen.episode import DatagenConfig, run_episode
    from datagen.workers import generate
    from sim.config import load_config
    from sim.seeding import resolve_seeds
    from sim.tasks import get_task, task_names

    tasks = task_names() if "all" in args.task else [get_task(t).name for t in args.task]
    seeds = resolve_seeds(args.seeds, args.episodes, args.seed_offset, default_episodes=None, default_offset=0)
    if args.planner == "llm" and not (args.llm_url and args.llm_model):
        print("sudd datagen: error: --planner llm needs --llm-url and --llm-model", file=sys.stderr)
        return 2
    cfg = load_config(DatagenConfig, {
        "dr": args.dr, "fidelity": args.fidelity, "max_retries": args.max_retries, "label": args.label,
        "perturb": args.perturb, "perturb_grasp": args.perturb_grasp,
        "path_noise_cm": args.path_noise_cm, "grasp_noise_cm": args.grasp_noise_cm, "handle_grasp": args.handle_grasp,
        "gripper": args.gripper, "gripper_speed": args.gripper_speed, "gripper_force": args.gripper_force,
        "holdout_colors": args.holdout_color, "holdout_shapes": args.holdout_shape,
        "planner": args.planner, "llm_url": args.llm_url, "llm_model": args.llm_model})
    summary = generate(tasks, len(seeds), args.out, args.workers, partial(run_episode, cfg=cfg),
                       ray_address=args.ray, seeds=seeds)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{summary['episodes']} new episodes ({summary['successes']} successful, {summary['errors']} errors, "
              f"{summary['skipped']} already present) in {summary['wall_s']:.0f} s -> {args.out}")
        print(f"inspect: sudd data info {args.out}")
    return 0 if summary["errors"] == 0 else 1
