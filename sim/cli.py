"""`sudd sim ...`: look at the simulated world: task families, randomized previews, oracle demos."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    sim = sub.add_parser("sim", help="the simulated world: tasks, DR previews, oracle demos",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    simsub = sim.add_subparsers(dest="sim_command", required=True, metavar="{tasks,preview,demo}")

    tasks = simsub.add_parser("tasks", help="list the task families with an example command each",
                              description="List the task families with an example command each.")
    tasks.set_defaults(func=_tasks)

    prev = simsub.add_parser(
        "preview", help="write a grid PNG of randomized first frames",
        description="Build COUNT randomized episodes (seeds SEED..SEED+COUNT-1) and tile their first frames from "
                    "the scene and wrist cameras into one PNG.",
        epilog="example:\n  sudd sim preview --task pick_place --dr heavy --seed 0 --out grid.png",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    prev.add_argument("--task", default="pick_place", help="task family (see `sudd sim tasks`)")
    prev.add_argument("--dr", default="heavy", help="DR preset off|light|heavy, or a TOML file of overrides")
    prev.add_argument("--seed", type=int, default=0, help="first episode seed")
    prev.add_argument("--count", type=int, default=12, help="number of episodes in the grid")
    prev.add_argument("--fidelity", default="full", choices=("full", "fast"), help="rendering fidelity")
    prev.add_argument("--out", type=Path, default=Path("grid.png"), help="output PNG path")
    prev.set_defaults(func=_preview)

    demo = simsub.add_parser(
        "demo", help="solve every task with its scripted oracle and save PNG strips",
        description="Solve each task family once with its privileged scripted oracle under domain randomization; "
                    "save a PNG strip of each episode and a summary.json.",
        epilog="example:\n  sudd sim demo --dr heavy --seed 3 --out out/demo",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    demo.add_argument("--task", action="append", help="task family (repeatable; default: all)")
    demo.add_argument("--dr", default="heavy", help="DR preset off|light|heavy, or a TOML file")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--fidelity", default="full", choices=("full", "fast"))
    demo.add_argument("--out", type=Path, default=Path("out/demo"))
    demo.set_defaults(func=_demo)


def _tasks(args) -> int:
    from sim.tasks import TASKS

    width = max(map(len, TASKS))
    for name, family in TASKS.items():
        print(f"{name:{width}s}  {family.description}")
        print(f"{'':{width}s}  e.g. sudd sim demo --task {name}    \"{family.example()}\"")
    return 0


def _preview(args) -> int:
    from sim.preview import preview_grid
    from sim.tasks import get_task

    get_task(args.task)  # fail early with the list of tasks
    path = preview_grid(args.task, args.dr, args.seed, args.out, count=args.count, fidelity=args.fidelity)
    print(f"wrote {path}")
    return 0


def _demo(args) -> int:
    from sim.demo import run_demo

    results = run_demo(args.out, args.task, args.seed, args.dr, args.fidelity)
    solved = sum(r["success"] for r in results.values())
    print(f"{solved}/{len(results)} tasks solved by their oracles; strips in {args.out}")
    return 0 if solved == len(results) else 1
