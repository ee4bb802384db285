"""sudd: from a language command to a real UR5 — simulate, generate data, distill a policy, deploy safely.

Each subcommand has its own --help with examples. Heavy libraries load only when a subcommand needs them.
"""

from __future__ import annotations

import argparse
import json
import sys

BENCH_AREAS = {
    "sim": "sim.bench:run_sim_bench",
    "datagen": "datagen.bench:run_datagen_bench",
    "bus": "runtime.bench_bus:run_bus_bench",
    "safety": "safety.bench:run_safety_bench",
    "policy": "policy.bench:run_policy_bench",
    "runtime": "runtime.bench_runtime:run_runtime_bench",
}


def build_parser() -> argparse.ArgumentParser:
    from datagen import cli as data_cli
    from datagen import generate_cli, views_cli
    from policy import cli as policy_cli
    from runtime import eval_cli, eval_compare, run_cli
    from sim import cli as sim_cli

    parser = argparse.ArgumentParser(
        prog="sudd", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  sudd sim tasks\n  sudd sim preview --task pick_place --dr heavy --out grid.png\n"
               "  sudd sim demo --out out/demo\n  sudd bench sim --json")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sim_cli.register(sub)
    generate_cli.register(sub)
    views_cli.register(sub)
    data_cli.register(sub)
    policy_cli.register(sub)
    run_cli.register(sub)
    eval_cli.register(sub)
    eval_compare.register(sub)

    bench = sub.add_parser("bench", help="measure speed and memory figures (medians, one run)",
                           description="Run a benchmark area and print its figures; --json prints one JSON object.",
                           epilog="examples:\n  sudd bench sim --json\n"
                                  "  sudd bench policy --policy policy/bundles/multitask   # the shipped bundle",
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    bench.add_argument("area", choices=sorted(BENCH_AREAS), help="what to measure")
    bench.add_argument("--json", action="store_true", help="print one JSON object (for scripts and CI)")
    bench.add_argument("--quick", action="store_true", help="fewer repetitions: a smoke run, not for figures")
    bench.add_argument("--policy", metavar="BUNDLE", default=None,
                       help="policy area: time this bundle (e.g. its goal query's goal_point) instead of a freshly "
                            "initialized small one")
    bench.set_defaults(func=_bench)
    return parser


def _bench(args) -> int:
    import importlib

    module_name, func = BENCH_AREAS[args.area].split(":")
    module = importlib.import_module(module_name)
    if args.policy and args.area != "policy":
        raise ValueError(f"--policy BUNDLE is for `sudd bench policy`, not {args.area}")
    kwargs = {"bundle": args.policy} if args.policy else {}
    figures = getattr(module, func)(quick=args.quick, **kwargs)
    if args.json:
        print(json.dumps(figures, indent=2))
    elif hasattr(module, "format_table"):
        print(module.format_table(figures))
    else:
        for key, value in _flatten(figures):
            print(f"{key:50s} {value}")
    return 0


def _flatten(d, prefix=""):
    for key, value in d.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def main(argv: list[str] | None = None) -> int:
    from sim.config import ConfigError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ConfigError, ValueError, KeyError) as exc:
        print(f"sudd {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
