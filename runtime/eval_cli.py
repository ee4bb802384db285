"""`sudd eval`: closed-loop success of a policy bundle in sim, against the data-collection policy, same seeds.

Each episode is one job (suite, task, seed, who). Results are appended to OUT/results.jsonl as they finish,
so an interrupted evaluation keeps what it did and a re-run with the same arguments resumes; OUT/summary.json,
OUT/results.md (the table) and OUT/success.png (the chart) are rewritten at the end. OUT/environment.json says
the machine and packages the run started on: a run resumed elsewhere says so (its episodes would not be the same
to the tick).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from dataclasses import asdict
from pathlib import Path

from runtime.machine_record import environment_change, library_versions

EPILOG = """\
suites (each on seeds OFFSET..OFFSET+N-1; keep OFFSET away from the training seeds):
  seen        the training distribution: objects and phrasings as in the data
  heldout     the target object has a colour/shape the data never had (recorded in the bundle from
              `sudd datagen --holdout-color/--holdout-shape`, or given here)
  heldout_shape  the target is a ball, a shape no training scene ever held, in a colour the data had
              (not for stack: a ball on a block is no stack)
  paraphrase  the command in a phrasing the data never used (the task family's `paraphrases`)

the data collector (planner + primitives + verify-and-retry with privileged state, `sudd datagen`'s policy,
its fingers moved as the gripper twin's are) runs on the same seeds for `seen` and the held-out suites; it cannot parse
unseen phrasings, so not for `paraphrase`.

examples:
  sudd eval --policy policy/bundles/demo --task pick_place --episodes 50 --dr heavy --seed-offset 100000
  sudd eval --policy out/bundle --task all --episodes 20 --suite seen --suite paraphrase --workers 2
  sudd eval --policy out/bundle --task pick_place --episodes 30 --suite heldout --holdout-color purple
  sudd eval --policy out/bundle --task pick_place --episodes 60 --latency-ms 6 --no-collector  # repeatable
  sudd eval --policy out/bundle --task pick_place --episodes 20 --filmstrips  # see each failure, frame by frame
  sudd eval --policy out/bundle --task drawer_put --seeds 100510 --latency-ms 6 --traces  # and tick by tick
  sudd eval --policy out/bundle --task drawer_open --episodes 10 --realtime --no-collector  # as deployed, live
"""


# The runtime's steps between the denoiser and the controller (runtime/shaping.py), each on; --no-NAME turns one off.
STEP_FLAGS = (
    ("served-pause", "play every chunk with its leading pause, even where the arm has already held still longer "
                     "than any pause of the collector's (runtime/served_pause.py)"),
    ("finger-wait", "let the arm follow the chunks while the fingers are still closing or opening, instead of "
                    "holding it until they stop (runtime/finger_wait.py)"),
    ("grasp-steer", "leave a retry after a close on nothing to the policy, instead of moving its approach over the "
                    "object the object query located (runtime/grasp_steer.py)"),
    ("release-guard", "let the policy open the fingers on the object anywhere, instead of holding back an opening in "
                      "the air far from the object query's drop point and carrying the object there "
                      "(runtime/release_guard.py)"),
    ("handle-height", "let the arm sink or rise while the fingers hold a drawer's handle, instead of keeping the "
                      "height they closed at (runtime/handle_height.py)"),
    ("free-pace", "play a slowed family (the drawers) at its pace everywhere, instead of at speed 1 while the hand "
                  "is high above the cell's fixtures (runtime/free_pace.py)"),
    ("empty-close", "leave fingers shut on nothing to the policy, instead of opening them where they are after 1 s, "
                    "as the data collector reopens after a missed grasp (runtime/empty_close.py)"),
)


def register(sub: argparse._SubParsersAction) -> None:
    from runtime import phases

    ev = sub.add_parser("eval", help="closed-loop success of a policy bundle in sim (with 95%% CIs), vs the data "
                                     "collector on the same seeds",
                        description="Run a policy bundle in closed loop in sim through the runtime's controller and "
                                    "the safety layer (runtime.evaluate), count task successes with 95% Wilson "
                                    "intervals, and compare with the data-collection policy on the same seeds.",
                        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    ev.add_argument("--policy", required=True, metavar="BUNDLE", help="policy bundle directory (sudd export)")
    ev.add_argument("--task", action="append", default=[], help="task family (repeatable) or 'all' (the bundle's "
                                                                "tasks; default)")
    ev.add_argument("--episodes", type=int, default=None, help="episodes per task and suite (default 20)")
    ev.add_argument("--dr", default="heavy", help="DR preset off|light|heavy or a TOML file (default heavy)")
    ev.add_argument("--seed-offset", type=int, default=None, help="first seed (default 100000)")
    ev.add_argument("--seeds", default=None, metavar="LIST|FILE",
                    help="exactly these seeds for every task instead of --episodes/--seed-offset: e.g. "
                         "100003,100015,100240-100259, or a file of them (one or more per line, # comments); to "
                         "re-run a bundle's failures, or a chosen part of the randomization")
    ev.add_argument("--suite", action="append", default=[], choices=["seen", "heldout", "heldout_shape", "paraphrase"],
                    help="what to test (repeatable; default: seen)")
    ev.add_argument("--holdout-color", action="append", default=[], metavar="COLOR",
                    help="colour kept out of the training data (default: what the bundle's data recorded); the "
                         "heldout suite targets it, the seen suite never shows it")
    ev.add_argument("--holdout-shape", action="append", default=[], metavar="SHAPE", help="likewise for shapes")
    ev.add_argument("--no-collector", action="store_true", help="skip the data-collection comparison")
    ev.add_argument("--time-limit-factor", type=float, default=1.0,
                    help="episode budget = task.max_seconds x this (default 1; the collector keeps datagen's 2)")
    ev.add_argument("--replan-every", type=int, default=1, metavar="TICKS",
                    help="policy ticks between inferences (1: every tick, as the runtime's policy node)")
    ev.add_argument("--latency-ms", type=float, metavar="MS",
                    help="simulated inference lag per chunk, fixed (default: each inference's measured wall time, "
                         "which varies from run to run; fix it, e.g. 6, to compare bundles on exactly the same "
                         "episodes)")
    ev.add_argument("--speed", default="", metavar="F|TASK=F,...",
                    help="pace the arm follows the policy's chunks at per task family, a fraction of the recorded "
                         "one in [0.1, 1] (default: the bundle's pace table; 0.5: actions and ticks 0.2 s apart, "
                         "observations as trained; TASK=F,... for some families; see sudd run --speed)")
    ev.add_argument("--no-goal-query", action="store_true",
                    help="condition on the head's own points where the bundle's goal query (policy/goal_query.py) "
                         "or object query (policy/object_query.py) would replace them: to measure what the queries "
                         "buy on the same seeds")
    ev.add_argument("--phases", action=argparse.BooleanOptionalAction, default=None, help=phases.HELP)
    for name, what in STEP_FLAGS:
        ev.add_argument(f"--no-{name}", action="store_true", help=f"{what}: to measure what it buys on the same seeds")
    ev.add_argument("--samples", type=int, default=1, metavar="K",
                    help="sample K chunks per policy tick in one batch and run the one most coherent with the chunk "
                         "before (policy/coherence.py; default 1: the plain sampler)")
    ev.add_argument("--filmstrips", action="store_true",
                    help="write OUT/filmstrips/SUITE_TASK_SEED.png for every failed policy episode: the scene and "
                         "wrist cameras every 2 s of sim time, to see how it failed (the episodes run the same "
                         "with or without)")
    ev.add_argument("--traces", action="store_true",
                    help="write OUT/traces/SUITE_TASK_SEED.csv for every failed policy episode: at every policy "
                         "tick the TCP, the fingers, the drawer, the named object, the chunk's first and last "
                         "targets and the controller's events (runtime/eval_trace.py), to read how it failed")
    ev.add_argument("--controller", type=Path, metavar="FILE.toml",
                    help="chunk controller settings (as sudd run --controller): a TOML file of "
                         "runtime/controller/config.py's fields; recorded in summary.json")
    ev.add_argument("--realtime", action="store_true",
                    help="run the policy's episodes through the stack `sudd run --sim` starts (processes, Zenoh, "
                         "the 500 Hz controller next to the physics and renderer) in real time, one after another, "
                         "instead of lockstep; the collector's stay lockstep. Slower (wall-clock episodes), and the "
                         "figure for this host: compare it with the lockstep one on the same seeds")
    ev.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    ev.add_argument("--out", type=Path, default=Path("out/eval"), help="results directory (default out/eval)")
    ev.add_argument("--json", action="store_true", help="print the summary as JSON")
    ev.set_defaults(func=_eval)


def _eval(args) -> int:
    from policy.bundle import Bundle
    from policy.coherence import check_samples
    from runtime.controller import ControllerConfig, load_controller, with_bundle_levels
    from runtime.eval_report import failure_table, markdown_table, plot, routing_note, summarise
    from policy.phased import resolve_phased
    from runtime.pace import check_speed_spec, resolve_pace
    from sim.seeding import resolve_seeds
    from sim.tasks import get_task

    if args.latency_ms is not None and not 0.0 <= args.latency_ms < 1000.0:
        raise ValueError(f"--latency-ms {args.latency_ms}: expected 0 <= MS < 1000 (the simulated inference lag of "
                         "one chunk); leave it out to use the measured time")
    check_speed_spec(args.speed)
    seeds = list(resolve_seeds(args.seeds, args.episodes, args.seed_offset, default_episodes=20,
                               default_offset=100_000))
    if args.realtime and (args.latency_ms is not None or args.filmstrips or args.traces):
        raise ValueError("--realtime: the lag is the stack's own and there are no filmstrips or traces of it; leave "
                         "out --latency-ms, --filmstrips and --traces (they are for the lockstep eval)")
    bundle = Bundle.load(args.policy, intra_op_num_threads=1)
    pace = resolve_pace(bundle.manifest, args.speed)
    phased = resolve_phased(bundle.phased, args.phases)
    controller = load_controller(args.controller) if args.controller is not None else ControllerConfig()
    controller = with_bundle_levels(controller, bundle.manifest)  # recorded in summary.json as used
    bundle.check_replan_every(args.replan_every)
    check_samples(args.samples)
    tasks = bundle.tasks if not args.task or "all" in args.task else [get_task(t).name for t in args.task]
    if not tasks:
        raise ValueError(f"{args.policy} records no tasks; name them with --task")
    suites = args.suite or ["seen"]
    recorded = bundle.manifest.get("data", {}).get("holdout") or {}
    held = {"colors": tuple(args.holdout_color or recorded.get("colors", ())),
            "shapes": tuple(args.holdout_shape or recorded.get("shapes", ()))}
    if "heldout" in suites and not (held["colors"] or held["shapes"]):
        raise ValueError(f"--suite heldout: {args.policy}'s data recorded no held-out colour or shape; give "
                         "--holdout-color/--holdout-shape (what `sudd datagen` kept out)")
    jobs = []  # seed-major: an eval stopped early (Ctrl-C, a deadline) has every task at about as many seeds
    mode = "realtime" if args.realtime else "lockstep"
    unshaped = [t for t in tasks if not get_task(t).novel_shapes] if "heldout_shape" in suites else []
    if unshaped:
        print(f"--suite heldout_shape: not for {', '.join(unshaped)} (no target a ball could stand for)",
              file=sys.stderr)
    for suite in suites:
        for seed in seeds:
            for task in tasks:
                if suite == "heldout_shape" and task in unshaped:
                    continue
                jobs.append({"suite": suite, "task": task, "seed": seed, "who": "policy", "mode": mode})
                if not args.no_collector and suite != "paraphrase":
                    jobs.append({"suite": suite, "task": task, "seed": seed, "who": "collector",
                                 "mode": "lockstep"})
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.jsonl"
    done = read_results(results_path)
    key = lambda j: (j["suite"], j["task"], j["seed"], j["who"], j.get("mode", "lockstep"))  # noqa: E731
    have = {key(r) for r in done}
    todo = [j for j in jobs if key(j) not in have]
    moved = environment_change(args.out, resuming=bool(have)) if todo else ""
    if moved:
        print(f"warning: {args.out} was started on another machine or install ({moved}); the episodes run now are "
              "not comparable tick for tick with those already there (the rates are): use a new --out to keep one "
              "run on one machine", file=sys.stderr)
    settings = {"bundle": str(args.policy), "dr": args.dr, "holdout": held,
                "time_limit_factor": args.time_limit_factor, "replan_every": args.replan_every,
                "latency_ms": args.latency_ms, "pace": pace.table, "goal_query": not args.no_goal_query,
                **{n.replace("-", "_"): not getattr(args, "no_" + n.replace("-", "_")) for n, _ in STEP_FLAGS},
                "samples": args.samples,
                "phases": list(phased), "realtime": args.realtime, "speed": args.speed,
                "filmstrips": str(args.out / "filmstrips") if args.filmstrips else None,
                "traces": str(args.out / "traces") if args.traces else None,
                "controller": asdict(controller)}
    from tqdm import tqdm

    t0 = time.perf_counter()
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="eval", unit="ep")
    wins = {"policy": 0, "collector": 0}
    try:
        with results_path.open("a") as f:
            for rec in _run_jobs(todo, settings, args.workers):
                f.write(json.dumps(rec) + "\n")
                f.flush()
                wins[rec["who"]] += bool(rec["success"])
                bar.update(1)
                bar.set_postfix(policy_ok=wins["policy"], collector_ok=wins["collector"])
    except KeyboardInterrupt:
        bar.close()
        print(f"interrupted: {bar.n} of {len(jobs)} episodes are in {results_path}; run the same command again to "
              "run the rest and write the tables", file=sys.stderr)
        return 130
    bar.close()
    wanted = {key(j) for j in jobs}
    records = [r for r in read_results(results_path) if key(r) in wanted]
    rows = summarise(records)
    table = markdown_table(rows)
    if routing_note(rows):
        table += "\n\n" + routing_note(rows)
    why = failure_table(rows)
    if why:
        table += ("\n\nWhy the policy failed (no_grasp: held nothing; wrong_object: held only other objects; "
                  "target_not_placed: held the named object, no success; closest approach: how near the TCP came to "
                  "the named object in the no_grasp episodes; yaw off: the gripper's yaw from the named object's grasp "
                  "yaw when it closed, modulo the object's symmetry):\n\n" + why)
    summary = {"settings": settings, "suites": suites, "tasks": tasks, "episodes": len(seeds),
               "seed_offset": seeds[0], "seeds": seeds, "wall_s": round(time.perf_counter() - t0, 1), "rows": rows,
               "bundle": bundle.info(), "versions": library_versions()}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    if bundle.goal_query is None:
        query = "Goal query: off (the bundle has none)"
    elif args.no_goal_query:
        query = "Goal query: off (--no-goal-query)"
    else:
        query = f"Goal query (policy/goal_query.py) for: {', '.join(bundle.goal_query.families)}"
    if bundle.object_query is not None:
        query += (". Object query (policy/object_query.py) for: " + ", ".join(bundle.object_query.families)
                  + (" (off: --no-goal-query)" if args.no_goal_query else ""))
    if args.realtime:
        query += (". Realtime (runtime/eval_realtime.py): the policy's episodes through the `sudd run --sim` "
                  "stack in real time; the time column is wall seconds")
    if phased:
        how = "--phases" if args.phases else "the bundle's manifest"
        query += f". Run as their phases (runtime/phases.py; {how}): {', '.join(phased)}"
    v = summary["versions"]
    measured = (f"Measured on {v['cpu']}, numpy {v['numpy']}, mujoco {v['mujoco']}, onnxruntime {v['onnxruntime']}: "
                "the same seeds give the same episodes only there.")
    (args.out / "results.md").write_text(f"# sudd eval: {args.policy}\n\n{measured}\n\nPolicy pace (fraction of "
                                         f"the recorded speed): {pace.describe()}. {query}\n\n{table}\n")
    png = plot(rows, args.out / "success.png")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(table)
        print(f"\n{len(records)} episodes; table {args.out / 'results.md'}, chart {png}, per episode {results_path}")
        if args.filmstrips:
            print(f"failed policy episodes, frame by frame: {args.out / 'filmstrips'}")
        if args.traces:
            print(f"failed policy episodes, tick by tick: {args.out / 'traces'}")
    return 0


def read_results(path: Path) -> list[dict]:
    """The episode records of an eval's results.jsonl ([] when there is none yet)."""
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass  # a line cut by a kill: that episode runs again
    return out


def _run_jobs(jobs: list[dict], settings: dict, workers: int):
    if settings.get("realtime"):  # the collector's episodes in lockstep first, then the live ones one by one
        yield from _run_jobs([j for j in jobs if j["mode"] != "realtime"], {**settings, "realtime": False}, workers)
        yield from _realtime_jobs([j for j in jobs if j["mode"] == "realtime"], settings)
        return
    if workers <= 1:
        _init(settings)
        for j in jobs:
            yield _job(j)
        return
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(settings,)) as pool:
        yield from pool.imap_unordered(_job, jobs)


def _realtime_jobs(jobs: list[dict], settings: dict):
    from runtime.controller import ControllerConfig
    from runtime.eval_realtime import run_realtime_episode
    from sim.config import load_config

    controller = load_config(ControllerConfig, settings["controller"])
    for j in jobs:
        t0 = time.perf_counter()
        out = run_realtime_episode(j, settings, controller)
        yield {**j, **out, "wall_s": round(time.perf_counter() - t0, 2)}


_WORKER: dict = {}


def _init_worker(settings: dict) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it stops the pool and keeps the results
    _init(settings)


def _init(settings: dict) -> None:
    from policy.bundle import Bundle

    from runtime.controller import ControllerConfig
    from sim.config import load_config

    _WORKER.clear()
    _WORKER.update(settings=settings, bundle=Bundle.load(settings["bundle"], intra_op_num_threads=1),
                   controller=load_config(ControllerConfig, settings["controller"]))


def _job(job: dict) -> dict:
    from runtime.evaluate import suite_holdout

    s = _WORKER["settings"]
    holdout = suite_holdout(job["suite"], s["holdout"])
    t0 = time.perf_counter()
    if job["who"] == "policy":
        out = _policy(job, s, holdout)
    else:
        out = _collector(job["task"], job["seed"], s["dr"], holdout)
    return {**job, **out, "wall_s": round(time.perf_counter() - t0, 2)}


def _policy(job: dict, s: dict, holdout) -> dict:
    from policy.pace import Pace
    from runtime.eval_filmstrip import Filmstrip
    from runtime.eval_trace import Trace
    from runtime.command_family import command_family
    from runtime.evaluate import episode_command, run_policy_episode
    from runtime.phases import phases_for
    from runtime.shaping import shaping_of

    strip = Filmstrip() if s["filmstrips"] else None
    trace = Trace() if s.get("traces") else None
    pace = Pace(s.get("pace", {}))
    bundle = _WORKER["bundle"]
    # the family the policy node would run the command as: a paraphrase may be judged another's
    command = episode_command(job["task"], job["seed"], s["dr"], holdout, paraphrase=job["suite"] == "paraphrase")
    family = command_family(bundle, command)
    phases = phases_for(family, pace, bundle.instructions, bundle.tasks) if family in s.get("phases", ()) else None
    try:
        out = run_policy_episode(bundle, job["task"], job["seed"], dr=s["dr"], holdout=holdout,
                                 command=command, runs_as=family or "", replan_every=s["replan_every"],
                                 time_limit_factor=s["time_limit_factor"],
                                 latency_s=None if s["latency_ms"] is None else s["latency_ms"] / 1e3,
                                 controller=_WORKER["controller"], observer=strip,
                                 speed=pace.speed(family), goal_query=s.get("goal_query", True),
                                 phases=phases, shaping=shaping_of(s),
                                 trace=trace).record()
        name = f"{job['suite']}_{job['task']}_{job['seed']}"
        if trace is not None and not out["success"]:
            out["trace"] = str(trace.save(Path(s["traces"]) / f"{name}.csv"))
        if strip is not None and not out["success"]:
            title = (f"{job['suite']} {job['task']} seed {job['seed']}: \"{out['command']}\" -> {out['end']}, "
                     f"{out['failure']}, held {', '.join(out['held']) or 'nothing'}")
            path = Path(s["filmstrips"]) / f"{name}.png"
            out["filmstrip"] = str(strip.save(path, title))
    finally:
        if strip is not None:
            strip.close()
    return out


def _collector(task: str, seed: int, dr: str, holdout) -> dict:
    from datagen.episode import DatagenConfig, run_episode
    from sim.config import load_config

    cfg = load_config(DatagenConfig, {"dr": dr})
    try:
        ep = run_episode(task, seed, cfg, holdout=holdout)
    except Exception as exc:  # a layout the collector cannot even start counts as its failure
        return {"success": False, "end": f"error: {exc!r}"[:300], "sim_seconds": None}
    return {"success": bool(ep.meta["success"]), "end": "success" if ep.meta["success"] else "failure",
            "sim_seconds": ep.meta.get("sim_seconds"), "command": ep.meta["instruction"],
            "retries": ep.meta.get("retries"), "gripper": cfg.gripper}
