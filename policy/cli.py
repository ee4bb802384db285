"""`sudd train` and `sudd export`: distill episodes into a diffusion policy, then into an ONNX bundle.

Register with `policy.cli.register(subparsers)` (runtime/cli.py); the bench is `policy.bench:run_policy_bench`.
torch is imported only when a command runs, so `sudd --help` stays fast.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    tr = sub.add_parser(
        "train", help="train a language-conditioned diffusion policy on an episode dataset (resumable)",
        description="Train (or resume) a diffusion policy. Checkpoints, metrics.jsonl and metrics.png go to --out;\n"
                    "re-running the same command continues from the last checkpoint.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  sudd train out/data --out runs/pp --steps 2000\n"
               "  sudd train out/data --out runs/pp --config full --epochs 100 --device cuda\n"
               "  sudd train out/data --out runs/pp --steps 2000 --nproc 2          # DDP (gloo on CPU)\n"
               "  sudd train out/data --out runs/pp --steps 500 --set batch_size=32 --set include_failures=true\n"
               "  sudd train out/mydata --out runs/ft --steps 3000 --config policy/bundles/demo \\\n"
               "      --init-from policy/bundles/demo        # fine-tune the shipped policy on your episodes")
    tr.add_argument("data", type=Path, help="episode dataset directory (sudd datagen --out)")
    tr.add_argument("--out", type=Path, required=True, help="run directory")
    tr.add_argument("--config", default="small", help=(
        "preset small|full, a TOML file, or a bundle directory (its training config) (default small)"))
    length = tr.add_mutually_exclusive_group(required=True)
    length.add_argument("--steps", type=int, help="optimizer steps in the schedule")
    length.add_argument("--epochs", type=int, help="passes over the samples")
    tr.add_argument("--stop-at", type=int, metavar="STEP", help=(
        "leave after STEP with a checkpoint, the schedule still --steps long (as a preemption would: the same "
        "command without it goes on); e.g. to rebuild a run that ended early"))
    tr.add_argument("--set", action="append", default=[], metavar="FIELD=JSON", help="override a config field")
    tr.add_argument("--fresh", action="store_true", help="start over instead of resuming")
    tr.add_argument("--init-from", type=Path, metavar="RUN|BUNDLE", help=(
        "warm-start a new run from RUN's latest EMA weights and stats (equal tensors copied, a grown "
        "conditioning input zero-initialized; see policy.warm_start), or from an exported BUNDLE's weights "
        "rebuilt from its graphs (e.g. policy/bundles/demo, to fine-tune the shipped policy); ignored when "
        "resuming"))
    tr.add_argument("--encoders-from", type=Path, metavar="PRETRAIN_RUN", help=(
        "with --init-from RUN: take the image encoders and aux head from this `sudd pretrain` run instead of RUN's "
        "(keep RUN's denoiser, e.g. after pretraining the encoders again on new views or with text_goal)"))
    tr.add_argument("--device", default="auto", help="auto|cpu|cuda|cuda:N (default auto)")
    tr.add_argument("--nproc", type=int, default=1, help="processes for DistributedDataParallel (torchrun)")
    tr.add_argument("--threads", type=int, metavar="N", help=(
        "torch intra-op threads (default: torch's, one per core). Give each job its share when jobs share a "
        "CPU: beside another 2-thread training on 2 cores, one took 4 s a step instead of 0.1 (OpenMP threads "
        "spin while they wait)"))
    tr.add_argument("--json", action="store_true", help="print the summary as JSON")
    tr.set_defaults(func=_train)

    pre = sub.add_parser(
        "pretrain", help="pretrain the image encoders and aux head on rendered views (sudd views)",
        description="Train the policy's image encoders and aux head to locate what the instruction names on\n"
                    "rendered views of every family they hold (policy/pretrain.py), validating on the episode\n"
                    "dataset's held-out episodes; then start a policy run from it with\n"
                    "`sudd train --init-from RUN`. Use the policy's config.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example:\n  sudd pretrain out/views --data out/data --out runs/pre --config "
               "policy/configs/demo_pick_place.toml --steps 3000\n"
               "  sudd train out/data --out runs/pp --config policy/configs/demo_pick_place.toml --steps 3000 "
               "--init-from runs/pre\n"
               "  sudd pretrain out/views_stack_home --data out/data_stack --out runs/locator --config "
               "policy/bundles/multitask \\\n      --init-from policy/bundles/multitask --goal-locator --steps 3000   "
               "# a goal locator\n"
               "  sudd pretrain out/views_stack_home --data out/data_stack --out runs/locator128 --config "
               "policy/bundles/multitask \\\n      --init-from policy/bundles/multitask --from-locator --goal-locator "
               "--steps 4000 --set 'crop_size=[128,128]'   # the shipped one, on the whole frame")
    pre.add_argument("views", type=Path, nargs="+",
                     help="views directories (sudd views --out), all used: e.g. approach and carrying views")
    pre.add_argument("--data", type=Path, required=True, help="the episode dataset the policy will train on")
    pre.add_argument("--out", type=Path, required=True, help="run directory (written afresh)")
    pre.add_argument("--config", default="small", help="the policy's preset or TOML file (default small)")
    pre.add_argument("--steps", type=int, required=True, help="optimizer steps")
    pre.add_argument("--set", action="append", default=[], metavar="FIELD=JSON", help="override a config field")
    pre.add_argument("--init-from", type=Path, metavar="RUN",
                     help="go on from an earlier pretrain run (its encoders and head; a fresh optimizer and "
                          "schedule of --steps), or from a bundle (e.g. policy/bundles/demo with --config "
                          "policy/bundles/demo) to teach its encoders more families' views")
    pre.add_argument("--episode-share", type=float, default=0.0, metavar="F", help=(
        "fill this share of every batch with recorded frames of --data's training episodes (default 0: views "
        "only); they show what renders at rest do not, e.g. a block held above the one to stack it on"))
    pre.add_argument("--episode-task", action="append", default=[], metavar="FAMILY", help=(
        "with --episode-share: recorded frames of this family only (repeatable; default every family)"))
    pre.add_argument("--head-only", action="store_true",
                     help="with --init-from: train the aux head alone, its encoders frozen (e.g. on carrying "
                          "views, to find the bin while carrying without moving the features the grasp reads; "
                          "measured: release 14.5 -> 10.4 cm, but the grasp point 2.35 -> 4.4 cm)")
    pre.add_argument("--goal-locator", action="store_true", help=(
        "train a goal locator for the goal query instead (policy/goal_locator.py): a copy of --init-from's encoders "
        "and head taught, on the views at home, where the role-swapped command's object is, validated by the query's "
        "error on --data's episodes; export it with `sudd export BUNDLE --goal-query stack ... --goal-locator RUN`"))
    pre.add_argument("--object-locator", action="store_true", help=(
        "train an object locator instead: the same copy taught where drawer_put's (and drawer_stow's) object is and "
        "where in the drawer it goes, from the start (views of `sudd views --task drawer_put --stage object "
        "--at-home`, `sudd views --task drawer_stow --at-home`), validated on --data's episodes of each; try it with "
        "`sudd oracle-eval BUNDLE --task drawer_put --phases --points-from RUN`"))
    pre.add_argument("--turn-locator", action="store_true", help=(
        "train a turn locator instead (policy/turn_query.py): the same copy taught how far the wrist must turn to "
        "grasp the command's object square to its faces, on views along the way to the grasp (`sudd views --task "
        "stack`), validated on --data's recorded frames before each first close; export it with `sudd export "
        "BUNDLE --queries-from BUNDLE --turn-locator RUN`"))
    pre.add_argument("--from-locator", action="store_true", help=(
        "with --goal-locator (or --object-locator, --turn-locator) and --init-from BUNDLE: start from the bundle's "
        "own locator of that question, rebuilt from its graph, instead of its policy's encoders and head (more "
        "views, or the whole frame with --set crop_size=[128,128], from where the shipped locator left off)"))
    pre.add_argument("--json", action="store_true", help="print the summary as JSON")
    pre.set_defaults(func=_pretrain)

    val = sub.add_parser(
        "validate", help="a run's or bundle's open-loop errors on a dataset's held-out episodes, per family",
        description="Hold a trained run (its EMA weights) or a bundle to the held-out episodes of an episode\n"
                    "dataset, as training validates (policy/validate.py): the aux head's grasp point before the\n"
                    "grasp, the release point while carrying, the sampled chunks against the recorded ones; on\n"
                    "data of several families each family's too. E.g. a pick_place bundle on five families' data.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example:\n  sudd validate policy/bundles/demo --data out/data_mt3 --val-fraction 0.1")
    val.add_argument("model", type=Path, help="a run directory (sudd train/pretrain --out) or a bundle")
    val.add_argument("--data", type=Path, required=True, help="the episode dataset to validate on")
    val.add_argument("--samples", type=int, default=1024, help="held-out samples (default 1024)")
    val.add_argument("--val-fraction", type=float, default=None,
                     help="which episodes are held out (default: the model's own val_fraction)")
    val.add_argument("--json", action="store_true", help="print the figures as JSON")
    val.set_defaults(func=_validate)

    orc = sub.add_parser(
        "oracle-eval", help="closed-loop episodes with the aux head's points replaced by the truth",
        description="Split a policy's failures into perception and control (policy/oracle_eval.py): run the\n"
                    "seen suite of `sudd eval` (same seeds, controller and safety filter) with the run's torch\n"
                    "checkpoint, giving the denoiser the sim's true grasp and release points instead of its aux\n"
                    "head's. Success well above `sudd eval`'s: the head is what fails; about the same: control.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  sudd oracle-eval out/run_fc5 --episodes 30 --inference-steps 16 --out out/oracle\n"
               "  sudd oracle-eval out/run_fc5 --episodes 30 --bias-cm 2 --out out/oracle_2cm   # perception 2 cm off\n"
               "  sudd oracle-eval out/run_fc5 --episodes 120 --true-points release --latency-ms 6 --workers 2 "
               "--out out/oracle_rel\n"
               "  sudd oracle-eval out/run_slow --task stack --episodes 20 --true-points release --latency-ms 6 "
               "--workers 2 --out out/oracle_stack   # does the block to stack on decide it?\n"
               "  sudd oracle-eval policy/bundles/multitask --task drawer_put --phases --offsets-data out/data_ft "
               "--episodes 20 --latency-ms 6 --workers 2 --out out/oracle_dput   # the skills, given the object")
    orc.add_argument("run", type=Path, help="training run directory or bundle (aux_condition, tcp frames)")
    orc.add_argument("--out", type=Path, required=True, help="directory for results.jsonl and results.md")
    orc.add_argument("--episodes", type=int, default=30, help="episodes, seeds seed-offset.. (default 30)")
    orc.add_argument("--seed-offset", type=int, default=100000, help="first seed (default 100000, as sudd eval)")
    orc.add_argument("--task", default="pick_place", choices=("pick_place", "stack", "drawer_put"),
                     help="the family (one that carries an object from a grasp to a release; default pick_place); "
                          "drawer_put's points are replaced while it takes the object to the drawer only")
    orc.add_argument("--phases", action="store_true",
                     help="run the command as the skills it is made of, switched by grasp cycles, each at its "
                          "family's pace in the bundle (runtime/phases.py; drawer_put: open, take, close)")
    orc.add_argument("--offsets-data", type=Path, metavar="DIR",
                     help="dataset to measure the grasp and release offsets on (default the run's own; a bundle "
                          "trained elsewhere needs one of this family)")
    orc.add_argument("--points-from", type=Path, metavar="RUN",
                     help="drawer_put: the object and drop an object locator run (sudd pretrain --object-locator) "
                          "finds at the start, in place of the truth")
    orc.add_argument("--bias-cm", type=float, default=0.0, help="move the true grasp point this far sideways")
    orc.add_argument("--true-points", choices=("both", "grasp", "release"), default="both",
                     help="which of the head's points the truth replaces (default both; with one, the other stays "
                          "the head's)")
    orc.add_argument("--latency-ms", type=float, metavar="MS",
                     help="a fixed simulated inference lag, as `sudd eval --latency-ms` (default: each one measured)")
    orc.add_argument("--inference-steps", type=int, help="DDIM steps (default the run's; match the bundle's)")
    orc.add_argument("--dr", default="heavy", help="DR preset off|light|heavy or a TOML file (default heavy)")
    orc.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    orc.set_defaults(func=_oracle_eval)

    cut = sub.add_parser(
        "cut-phases", help="cut a phased family's episodes into the skills its phases run, as their own episodes",
        description="Write each verified episode of a phased family (policy/phased.py; drawer_put) of SRC,\n"
                    "cut to a phase that runs another family's skill, into OUT as an episode of that family\n"
                    "with the phase's text (policy/phase_data.py): drawer_put's closing cycle, from the step\n"
                    "the object is let go (where the runtime switches phase), as a \"close the drawer\"\n"
                    "episode of drawer_close, the object in the drawer. A phase of the family itself with a\n"
                    "text of its own (policy.phased.OWN_PHASE_TEXT) is cut when asked (--phase drawer_put:1:\n"
                    "\"pick up the red block and put it in the open drawer\"); a bundle trained on it runs that\n"
                    "phase under that text. Merge OUT into the training data.\n"
                    "Re-running continues; an episode whose grasp cycles and subtask labels disagree is skipped.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  sudd cut-phases out/data_dput --out out/data_dput_phases             # every skill phase\n"
               "  sudd cut-phases out/data_dput --phase drawer_put:2 --out out/data_close   # the closing only\n"               "  sudd cut-phases out/data_dput --phase drawer_put:0 --phase drawer_put:1 --phase drawer_put:2 \\\n"
               "      --out out/data_dput_all                                              # the middle cycle too\n"
               "  sudd data merge out/data_reh out/data_close --out out/data_ft")
    cut.add_argument("source", type=Path, metavar="SRC", help="episode dataset directory")
    cut.add_argument("--out", type=Path, required=True, help="the new dataset's directory")
    cut.add_argument("--phase", action="append", default=None, metavar="FAMILY:K",
                     help="cut phase K (0-based, a count of grasp cycles) of FAMILY; repeatable (default: every "
                          "phase that runs another family's skill)")
    cut.set_defaults(func=_cut_phases)

    from policy.export_cli import register as register_export

    register_export(sub)


def parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item!r}: expected FIELD=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value  # a bare string
    return out


def _train(args) -> int:
    if args.nproc > 1:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.nproc}",
               "-m", "policy.train", str(args.data), str(args.out), "--config", str(args.config),
               "--device", args.device]
        cmd += ["--steps", str(args.steps)] if args.steps else ["--epochs", str(args.epochs)]
        cmd += [a for s in args.set for a in ("--set", s)] + (["--fresh"] if args.fresh else [])
        cmd += ["--init-from", str(args.init_from)] if args.init_from else []
        cmd += ["--encoders-from", str(args.encoders_from)] if args.encoders_from else []
        cmd += ["--stop-at", str(args.stop_at)] if args.stop_at is not None else []
        return subprocess.call(cmd, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    from policy.train import train

    if args.threads is not None and args.threads < 1:
        raise ValueError(f"--threads {args.threads}: expected a positive number of threads")
    if args.stop_at is not None and args.stop_at < 1:
        raise ValueError(f"--stop-at {args.stop_at}: expected a step >= 1")
    summary = train(args.data, args.config, args.out, steps=args.steps, epochs=args.epochs, resume=not args.fresh,
                    device=args.device, overrides=parse_overrides(args.set), init_from=args.init_from,
                    encoders_from=args.encoders_from, threads=args.threads, stop_at=args.stop_at)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        val = summary.get("validation") or {}
        sampled = f", sampled chunks {val['val_chunk_cm']:.1f} cm from the recorded (unseen episodes)" \
            if "val_chunk_cm" in val else ""
        print(f"run {summary['run_dir']}: step {summary['step']}/{summary['total_steps']}, "
              f"loss {summary['final_loss']:.4f}{sampled}, checkpoint {summary.get('checkpoint')}, "
              f"plot {summary['plot']}")
    return 0


def _pretrain(args) -> int:
    from policy.pretrain import pretrain

    asked = [q for q, flag in (("goal", args.goal_locator), ("object", args.object_locator),
                                ("turn", args.turn_locator)) if flag]
    if len(asked) > 1:
        raise ValueError(f"--{'-locator, --'.join(asked)}-locator each train one locator: give one of them")
    summary = pretrain(args.views, args.data, args.config, args.out, args.steps, parse_overrides(args.set),
                       init_from=args.init_from, head_only=args.head_only, episode_share=args.episode_share,
                       episode_tasks=tuple(args.episode_task), goal_locator=bool(asked),
                       locator_question=asked[0] if asked else "goal", from_locator=args.from_locator)
    val = summary["validation"] or {}
    if asked:
        print(json.dumps(summary, indent=2) if args.json else _locator_line(asked[0], summary, args))
        return 0
    print(json.dumps(summary, indent=2) if args.json else
          f"run {summary['run_dir']}: {summary['views']} views of {summary['scenes']} scenes, loss "
          f"{summary['final_loss']:.4f}, held-out grasp error {val.get('val_grasp_cm', float('nan')):.1f} cm "
          f"({val.get('val_pregrasp_cm', float('nan')):.1f} cm before the grasp), release point "
          f"{val.get('val_release_cm', float('nan')):.1f} cm off while carrying; "
          + (f"grasp yaw {val['val_axis_deg']:.0f} deg off on bars; " if "val_axis_deg" in val else "")
          + f"next: sudd train {args.data} --out RUN --init-from {summary['run_dir']}")
    return 0


def _locator_line(question: str, s: dict, args) -> str:
    """What a locator's pretraining run learnt, in one line, and the export that ships it."""
    b, val = s["goal_query_before"], s["validation"] or {}
    if question == "turn":
        return (f"turn locator {s['run_dir']} ({s['views']} views on the way to the grasp), on {args.data}'s frames "
                f"before the first close: the wrist turn {b['turn_deg_median']:.1f} -> {val['turn_deg_median']:.1f} "
                f"deg off, at the start {b['turn_deg_start_median']:.1f} -> {val['turn_deg_start_median']:.1f} "
                f"(medians; not turning: {val['no_turn_deg_median']:.1f}); next: sudd export {args.init_from} --out "
                f"BUNDLE --queries-from {args.init_from} --turn-locator {s['run_dir']}")
    if question == "object":
        prefixes = ["object_"] + sorted({k[:-len("grasp_cm_median")] for k in val
                                         if k.endswith("_grasp_cm_median") and k != "object_grasp_cm_median"})
        return (f"object locator {s['run_dir']} ({s['views']} home views), on {args.data}'s episodes (medians; the "
                f"first family, then each other): " + "; ".join(
                    f"{p[len('object_'):-1] or 'first'}: the object {b[p + 'grasp_cm_median']:.2f} -> "
                    f"{val[p + 'grasp_cm_median']:.2f} cm off, the drop {b[p + 'release_cm_median']:.2f} -> "
                    f"{val[p + 'release_cm_median']:.2f} cm" for p in prefixes))
    where = "the look pose " + str(s["look_m"]) if s.get("look_m") else "home"
    return (f"goal locator {s['run_dir']} ({s['views']} views from {where}): the goal query's release point on "
            f"{args.data} {b['goal_cm_median']:.2f} -> {val['goal_cm_median']:.2f} cm off (median; p75 "
            f"{b['goal_cm_p75']:.2f} -> {val['goal_cm_p75']:.2f}); next: sudd export {args.init_from} --out BUNDLE "
            f"--goal-query FAMILY --goal-query-data DATA --goal-locator {s['run_dir']}")


def _validate(args) -> int:
    from policy.validate import validate_model

    if args.samples < 1:
        raise ValueError(f"--samples must be >= 1, got {args.samples}")
    out = {k: round(v, 3) for k, v in validate_model(args.model, args.data, args.samples, args.val_fraction).items()
           if k.startswith("val_") or k.startswith("guess_")}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for key, value in out.items():
            print(f"{key:36s} {value:8.2f}")
    return 0


def _oracle_eval(args) -> int:
    from policy.oracle_eval import oracle_eval
    from runtime.eval_report import markdown_table

    for name in ("episodes", "workers"):
        if getattr(args, name) < 1:
            raise SystemExit(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.bias_cm < 0:
        raise SystemExit(f"--bias-cm must be >= 0, got {args.bias_cm}")
    if args.latency_ms is not None and not 0.0 <= args.latency_ms <= 1000.0:
        raise SystemExit(f"--latency-ms must be in [0, 1000], got {args.latency_ms}")
    rows = oracle_eval(args.run, args.out, args.episodes, args.seed_offset, args.bias_cm, args.inference_steps,
                       args.dr, args.workers, true_points=args.true_points, latency_ms=args.latency_ms,
                       task=args.task, phases=args.phases, offsets_data=args.offsets_data,
                       points_from=args.points_from)
    print(markdown_table(rows))
    print(f"per episode {args.out / 'results.jsonl'}; compare with `sudd eval` on the same seeds")
    return 0


def _cut_phases(args) -> int:
    from tqdm import tqdm

    from datagen.store import Dataset, StoreError
    from policy.phase_data import cut_phases, parse_phase_args

    try:
        phases = parse_phase_args(args.phase)
        total = len(Dataset(args.source))
        with tqdm(total=total, unit="ep", desc="cut phases") as bar:
            report = cut_phases(args.source, args.out, phases, progress=bar.update)
    except (StoreError, ValueError) as exc:
        print(f"sudd cut-phases: error: {exc}", file=sys.stderr)
        return 2
    written = ", ".join(f"{n} {f}" for f, n in sorted(report.written.items())) or "none"
    skipped = ", ".join(f"{n} {why}" for why, n in sorted(report.skipped.items())) or "none"
    print(f"{args.out}: wrote {written} (skipped: {skipped}; {report.kept_before} there before); content hash "
          f"{Dataset(args.out).content_hash()}")
    return 0
