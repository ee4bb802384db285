"""`sudd views`: render labelled views of heavy-DR scenes of one task family (no physics, no planning) to
pretrain the policy's image encoder to find what the instruction names (see datagen/views.py, then
`sudd pretrain`): the object and its bin (pick_place), the two blocks (stack), the drawer's handle
(drawer_open, drawer_close, drawer_put), the object and the open drawer's floor (drawer_stow). Render each
family into the same directory, one command each. A long task's later grasps have views of their own (--stage;
datagen/views_stages.py): drawer_put's object, with the drawer open, and its handle again, with the object in
the open drawer. --at-home renders, for the object locator (sudd pretrain --object-locator), the scene as it
starts labelled with the grasp whose object lies where it starts: drawer_put's object, drawer_stow's.

The labels' offsets (where an episode closes and opens the gripper, relative to the object and the bin, the
blocks, the handle) are measured on recorded episodes of the family (--offsets-from). Shards of 50 scenes land
as they finish; re-running the same command skips the shards already there. Hold out the same colours as the
episode data, so the held-out evaluation stays held out.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from policy.goal_query import MAX_LOOK_M  # the goal query's limit: these views are its locator's

    v = sub.add_parser(
        "views", help="render labelled views of DR scenes for encoder pretraining (sudd pretrain)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example:\n  sudd views --out out/views --scenes 3000 --seed-offset 200000 --offsets-from out/data "
               "--holdout-color purple\n  sudd views --out out/views_carry --scenes 2000 --views 1 --carry-views 4 "
               "--seed-offset 203000 --offsets-from out/data --holdout-color purple\n"
               "  sudd views --task drawer_open --out out/views --scenes 600 --seed-offset 210000 "
               "--offsets-from out/data_do --holdout-color purple\n"
               "  sudd views --task drawer_put --stage object --out out/views --scenes 600 --seed-offset 212000 "
               "--offsets-from out/data_dput --holdout-color purple\n"
               "  sudd views --task drawer_stow --at-home --views 1 --out out/views_home --scenes 4000 "
               "--seed-offset 800000 --offsets-from out/data_stow --holdout-color purple")
    v.add_argument("--task", default="pick_place",
                   help="task family: pick_place (default), stack, drawer_open, drawer_close, drawer_put or "
                        "drawer_stow")
    v.add_argument("--stage", default="", metavar="STAGE",
                   help="a long task's later grasp to render the way to: drawer_put's object (the drawer open) or "
                        "close (the object in the open drawer, the handle again); default the first grasp")
    v.add_argument("--at-home", action="store_true",
                   help="the scene as the episode starts (the arm at home) with the labels of the grasp whose object "
                        "lies where it starts: drawer_put's with --stage object (its drawer still shut), "
                        "drawer_stow's first; for an object locator (sudd pretrain --object-locator)")
    v.add_argument("--look", default="", metavar="DX,DY,DZ",
                   help="render each scene's first view with the TCP this far from home (metres, base frame, each "
                        f"within {MAX_LOOK_M} m; e.g. 0.15,0.08,0.1): the look pose of a goal locator "
                        "(sudd pretrain --goal-locator) that asks from there, where home's wrist camera misses "
                        "part of the table")
    v.add_argument("--out", type=Path, required=True, help="views directory (created; resumed if present)")
    v.add_argument("--scenes", type=int, required=True, help="scenes to render (one seed each)")
    v.add_argument("--views", type=int, default=6, help="views per scene, the first at home (default 6)")
    v.add_argument("--carry-views", type=int, default=0, metavar="N",
                   help="also N views per scene with the named object held on its way to its release (the bin, "
                        "the block to stack on; pick_place and stack only; default 0; see datagen/views_carry.py)")
    v.add_argument("--seed-offset", type=int, default=200000,
                   help="first seed (default 200000); keep it away from training and evaluation seeds")
    v.add_argument("--offsets-from", type=Path, required=True, metavar="DATA",
                   help="an episode dataset with successful episodes of --task to measure the label offsets on")
    v.add_argument("--holdout-color", action="append", default=[], metavar="COLOR",
                   help="never use this object colour (repeatable; as for sudd datagen)")
    v.add_argument("--holdout-shape", action="append", default=[], metavar="SHAPE",
                   help="never use this object shape (repeatable)")
    v.add_argument("--json", action="store_true", help="print the summary as JSON")
    v.set_defaults(func=_views)


def _views(args) -> int:
    from datagen.view_anchors import FAMILIES, check_carries
    from datagen.views import generate, measure_offsets
    from datagen.views_stages import OBJECT_AT_START, label_key, stage_index
    from sim.config import load_config
    from sim.tasks import Holdout

    if args.scenes < 1 or args.views < 1 or args.carry_views < 0:
        raise ValueError(f"--scenes and --views must be >= 1 and --carry-views >= 0 (got {args.scenes}, "
                         f"{args.views}, {args.carry_views})")
    holdout = load_config(Holdout, {"colors": args.holdout_color, "shapes": args.holdout_shape})
    if args.task not in FAMILIES:
        raise ValueError(f"--task {args.task}: views label the families {', '.join(FAMILIES)}; pick one of them")
    if args.carry_views:
        try:
            check_carries(args.task)
        except ValueError as exc:
            raise ValueError(f"--carry-views: {exc}; leave it out") from None
    from policy.goal_query import parse_look

    look = parse_look(args.look) if args.look else None
    key = label_key(args.task, args.stage)
    if args.at_home and stage_index(args.task, args.stage) != OBJECT_AT_START.get(args.task):
        raise ValueError(f"--at-home labels an object's grasp from the start: give --task drawer_put --stage object "
                         f"or --task drawer_stow (got --task {args.task} --stage {args.stage or '(first)'})")
    offsets = measure_offsets(args.offsets_from, key)
    shards = generate(args.out, range(args.seed_offset, args.seed_offset + args.scenes), args.views, offsets,
                      holdout, carry=args.carry_views, task=args.task, stage=args.stage, at_home=args.at_home,
                      look=look)
    summary = {"out": str(args.out), "task": args.task, "stage": key, "at_home": args.at_home,
               "look_m": list(look) if look else None, "shards": len(shards),
               "scenes": args.scenes,
               "views_per_scene": args.views,
               "carry_views_per_scene": args.carry_views,
               "offsets_m": {k: [round(float(x), 4) for x in offsets[k]] for k in ("grasp", "release")},
               "offsets_episodes": int(offsets["episodes"])}
    print(json.dumps(summary, indent=2) if args.json else
          f"{args.scenes} scenes x {args.views} views in {len(shards)} shards -> {args.out}; next: "
          f"sudd pretrain {args.out} --data {args.offsets_from} --out runs/pretrain --config "
          f"policy/configs/demo_pick_place.toml --steps 3000")
    return 0
