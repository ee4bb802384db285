"""`sudd data ...`: look at a generated dataset (per-task statistics, episode contact sheets) or merge several."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="inspect a generated dataset (statistics, contact sheets) or merge several",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    datasub = data.add_subparsers(dest="data_command", required=True, metavar="{info,show,merge}")

    info = datasub.add_parser(
        "info", help="episodes, success rates and per-task statistics of a dataset",
        description="Print the committed episodes of dataset DIR per task: count, success rate, mean length, "
                    "mean retries and how often the plan's check snippets agree with the ground-truth "
                    "predicate; plus the dataset's content hash. Unreadable shards are named and skipped.",
        epilog="examples:\n  sudd data info out/data\n  sudd data info out/data --json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    info.add_argument("dir", type=Path, metavar="DIR", help="dataset directory (the one holding shards/)")
    info.add_argument("--json", action="store_true", help="print one JSON object (for scripts and CI)")
    info.set_defaults(func=_info)

    show = datasub.add_parser(
        "show", help="write a PNG contact sheet of one episode",
        description="Write a PNG of episode N: scene and wrist camera frames at evenly spaced times, each "
                    "captioned with the time and the subtask being executed, under the root instruction, "
                    "task, seed and success. Episode numbers are those of `sudd data info` order (0..E-1).",
        epilog="example:\n  sudd data show out/data --episode 3 --out ep3.png",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    show.add_argument("dir", type=Path, metavar="DIR", help="dataset directory (the one holding shards/)")
    show.add_argument("--episode", type=int, required=True, metavar="N", help="episode index, 0-based")
    show.add_argument("--samples", type=int, default=10, help="time samples (columns) in the sheet (default: 10)")
    show.add_argument("--out", type=Path, default=None, help="output PNG (default: episode<N>.png)")
    show.set_defaults(func=_show)

    merge = datasub.add_parser(
        "merge", help="copy several datasets into one, e.g. to train on all of them",
        description="Copy every episode of the SRC datasets into one shard of the new dataset OUT "
                    "(OUT/shards/merged.zarr); `sudd train OUT` then sees them all. A (task, seed) pair found in "
                    "two sources, or in a source and an existing OUT, with different content is refused before "
                    "anything is copied (two generations of the same seeds, e.g. with and without "
                    "--path-noise-cm: pick one). Re-running an "
                    "interrupted merge continues it; the merged content hash is printed (it equals the hash of "
                    "the sources' union, whatever the sharding).",
        epilog="examples:\n  sudd data merge out/data_a out/data_b --out out/data_ab\n"
               "  sudd data merge out/data_ab --task pick_place --out out/data_c   # then another source into it",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    merge.add_argument("sources", type=Path, nargs="+", metavar="SRC", help="dataset directories to copy from")
    merge.add_argument("--out", type=Path, required=True, help="the merged dataset's directory")
    merge.add_argument("--task", action="append", default=None, metavar="TASK",
                       help="copy only this task's episodes (repeatable; default: every task). Merging more into "
                            "an existing OUT adds to it, so a family can be swapped for a new generation of it")
    merge.set_defaults(func=_merge)


def _errors(func):
    """Report a missing/unreadable dataset or a bad episode number as one line and exit code 2."""
    def wrapper(args) -> int:
        from datagen.store import StoreError

        try:
            return func(args)
        except (StoreError, IndexError) as exc:
            print(f"sudd data {args.data_command}: error: {exc}", file=sys.stderr)
            return 2
    return wrapper


@_errors
def _info(args) -> int:
    from datagen.inspect import dataset_info, format_info

    info = dataset_info(args.dir)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


@_errors
def _show(args) -> int:
    from datagen.inspect import contact_sheet

    out = args.out or Path(f"episode{args.episode}.png")
    print(f"wrote {contact_sheet(args.dir, args.episode, out, samples=args.samples)}")
    return 0


@_errors
def _merge(args) -> int:
    from tqdm import tqdm

    from datagen.merge import merge_datasets
    from datagen.store import Dataset

    sources = [Dataset(src) for src in args.sources]
    with tqdm(total=sum(len(ds) for ds in sources), unit="ep", desc="merge") as bar:
        merged = merge_datasets(sources, args.out, progress=bar.update, tasks=args.task)
    print(f"{args.out}: {len(merged)} episodes from {len(args.sources)} dataset(s); content hash "
          f"{merged.content_hash()}")
    return 0
