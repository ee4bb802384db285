"""`sudd run` (the whole runtime stack) and `sudd say` (a language command on the bus)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import uuid
from pathlib import Path

DEFAULT_BUNDLE = Path("policy/bundles/multitask")
BUNDLE_ENV = "SUDD_POLICY"
NODE_KINDS = ("robot", "camera", "policy")

RUN_EPILOG = """\
examples:
  sudd run --sim --policy out/bundle --duration 30
  sudd run --sim --task stack --seed 3 --policy out/bundle --command "put the green block on the blue block"
  sudd run --robot-ip 192.168.1.10 --camera-serial scene=123456789012 --camera-serial wrist=234567890123 \\
           --policy out/bundle                        # connects and holds: no motion
  sudd run ... --allow-motion                         # the policy may move the arm (through safety)

policy on another computer (a GPU box), controller on the robot's:
  robot PC:  sudd run --robot-ip 192.168.1.10 --camera-serial ... --nodes robot,camera --hub tcp/0.0.0.0:7447
  GPU box:   sudd run --connect tcp/ROBOT-PC:7447 --nodes policy --policy out/bundle
  (the robot PC's launcher sends the command until the policy node answers; open port 7447 and the nodes'
   ephemeral ports between the two; the same works with --sim on the robot PC)

policy bundle: --policy, else $SUDD_POLICY, else policy/bundles/multitask if it exists. Make one with
  sudd train out/data --out out/run  &&  sudd export out/run --out out/bundle

hardware bring-up checklist (before --allow-motion):
  1. E-stop within reach and tested; workspace clear; speed slider at 10-30 % on the teach pendant.
  2. Robot in Remote Control, ur_rtde reachable (ping ROBOT_IP; ports 30004/29999 open); the Robotiq
     URCap installed and its socket on port 63352.
  3. Safety limits of your cell (copy safety/limits_example.toml: workspace box, keep-out boxes, TCP speed),
     given with --limits cell.toml; the controller's servo lag for your arm with --controller ur5.toml
     (execution_latency = 0.1 is nearer a real UR than the sim's 0.016).
  4. Cameras: `rs-enumerate-devices` lists each serial; the scene camera at its calibrated pose
     (sudd calibration); the hand-eye result loaded.
  5. First run WITHOUT --allow-motion: state and frames flow (watch `sudd say` answers and the events);
     the arm must not move.
  6. Then --allow-motion with a trained task; keep a hand on the E-stop. Ctrl-C = controlled stop first.
"""


def register(sub: argparse._SubParsersAction) -> None:
    from runtime import phases

    run = sub.add_parser("run", help="run the runtime: robot + policy (+ camera) nodes, on the sim or hardware",
                         description="Start every node as its own process over real Zenoh sessions, wait for "
                                     "them, run, then stop: the robot node's controlled stop first (Ctrl-C too).",
                         epilog=RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = run.add_mutually_exclusive_group()
    mode.add_argument("--sim", action="store_true", help="the sim twins (realtime SimRig, sim cameras)")
    mode.add_argument("--robot-ip", metavar="IP", help="a real UR (ur_rtde) with a Robotiq 2F-85 on its URCap")
    run.add_argument("--task", default="pick_place", help="sim task family (default pick_place)")
    run.add_argument("--seed", type=int, default=0, help="sim episode seed")
    run.add_argument("--dr", default="off", help="sim domain randomization preset or TOML (default off)")
    run.add_argument("--policy", metavar="BUNDLE", help=f"policy bundle dir (default ${BUNDLE_ENV} or {DEFAULT_BUNDLE})")
    run.add_argument("--command", metavar="TEXT", help="language command (sim default: the episode's instruction)")
    run.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: "
                     "until Ctrl-C; sim: also stops at task success)")
    run.add_argument("--camera-serial", action="append", default=[], metavar="NAME=SERIAL",
                     help="hardware: RealSense serial per bundle camera (scene=..., wrist=...)")
    run.add_argument("--allow-motion", action="store_true", help="hardware: let the policy move the arm")
    run.add_argument("--hub", default="tcp/127.0.0.1:7447", help="where this launcher's bus listens (sudd say and "
                     "--connect join there); a network address such as tcp/0.0.0.0:7447 lets other computers in (no "
                     "authentication: only on the robot's own network)")
    run.add_argument("--connect", metavar="ENDPOINT", help="join the bus of a `sudd run` on another computer "
                     "instead of holding one here (e.g. tcp/robot-pc:7447 with --nodes policy)")
    run.add_argument("--nodes", default=",".join(NODE_KINDS), metavar="LIST",
                     help=f"which nodes to start here, comma-separated from {', '.join(NODE_KINDS)} (default all)")
    run.add_argument("--controller", type=Path, metavar="FILE.toml",
                     help="chunk controller settings: a TOML file of runtime/controller/config.py's fields, e.g. "
                          "execution_latency = 0.1 (a real UR's servo lag; its estimate is in the controller "
                          "telemetry) or gripper_min_hold = 0.6; the rest keep their defaults")
    run.add_argument("--limits", type=Path, metavar="FILE.toml",
                     help="safety limits of your cell (workspace box, keep-out boxes, speeds): a TOML file as "
                          "safety/limits_example.toml; missing keys keep the defaults for the arm's variant")
    run.add_argument("--replan-every", type=int, default=1, metavar="TICKS",
                     help="infer on every Nth policy tick only (1 to the bundle's action horizon; default 1): "
                          "less CPU, the same action rate (the shipped bundle: 13/60 with 4, 12/60 with 1)")
    run.add_argument("--speed", default="", metavar="F|TASK=F,...",
                     help="pace the arm follows the policy at, a fraction of its demonstrations' in [0.1, 1], per "
                          "task family (a command's family: its closest trained instruction's). Default: the "
                          "bundle's pace table (the shipped bundle: drawer_close 0.5, drawer_open 0.75, the rest "
                          "1: so its drawers open 20/20 and close 19/20 on fresh seeds, against 12/20 and 10/20 "
                          "at full speed, while pick_place at 0.5 falls from 20/20 to 13/20; "
                          "policy/EXPERIMENTS.md, \"The pace per task family\"). F: every family at F; "
                          "TASK=F,...: those families (\"*=F\" the others), e.g. --speed drawer_close=0.4,*=0.8")
    run.add_argument("--no-goal-query", action="store_true",
                     help="condition on the policy's own release point where the bundle asks its head where a "
                          "stack goes (the manifest's goal_query; policy/goal_query.py: step 23's bundle stacked "
                          "8/20 with it, 1/20 without), and where a bundle has an object query its locator's "
                          "points for a long task's later object (policy/object_query.py); with it goes the "
                          "goal query's look (the shipped bundle's stack: the arm to a pose 10 cm up and back, "
                          "~4 s, before the policy's first chunk; runtime/look.py)")
    run.add_argument("--phases", action=argparse.BooleanOptionalAction, default=None,
                     help=f"{phases.HELP}: the shipped bundle's drawer_put (policy/EXPERIMENTS.md, \"drawer_put's "
                          "object from the start\")")
    run.add_argument("--robot", default="ur5", help="robot name in the bus keys (sudd/<robot>/...)")
    run.add_argument("--json", action="store_true", help="print the final reports as JSON")
    run.set_defaults(func=_run)

    say = sub.add_parser("say", help="send a language command to a running `sudd run` and print the answer",
                         epilog='example:\n  sudd say "put the red block in the left bin"',
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    say.add_argument("text", help="the command")
    say.add_argument("--robot", default="ur5", help="robot name in the bus keys")
    say.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the launcher's hub endpoint")
    say.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the policy node's answer")
    say.set_defaults(func=_say)


def resolve_bundle(arg: str | None) -> Path:
    for cand in (arg, os.environ.get(BUNDLE_ENV), str(DEFAULT_BUNDLE) if DEFAULT_BUNDLE.is_dir() else None):
        if cand:
            p = Path(cand)
            if not (p / "manifest.json").is_file():
                raise ValueError(f"{p} is not a policy bundle (no manifest.json)")
            return p
    raise ValueError(f"no policy bundle: pass --policy BUNDLE (or set ${BUNDLE_ENV}); the shipped one is "
                     f"{DEFAULT_BUNDLE} (restore its text encoder with `make setup`). Make your own with "
                     "`sudd datagen ...`, `sudd train DATA --out RUN` and `sudd export RUN --out BUNDLE`")


def parse_nodes(text: str, sim: bool, robot_ip: str | None) -> set[str]:
    """The node kinds of `--nodes`, checked against the mode; ValueError says what to change."""
    kinds = {k.strip() for k in text.split(",") if k.strip()}
    if not kinds or kinds - set(NODE_KINDS):
        raise ValueError(f"--nodes {text!r}: expected a comma-separated subset of {', '.join(NODE_KINDS)}")
    if kinds - {"policy"} and not (sim or robot_ip):
        raise ValueError(f"--nodes {','.join(sorted(kinds))} runs the robot side: add --sim or --robot-ip IP "
                         "(only `--nodes policy` runs without either)")
    return kinds


def _run(args) -> int:
    from runtime.launch import (Launcher, NodeFailed, bundle_manifest, hardware_stack, node_kind, policy_stack,
                                sim_stack)

    try:
        kinds = parse_nodes(args.nodes, args.sim, args.robot_ip)
    except ValueError as exc:
        print(f"sudd run: {exc}", file=sys.stderr)
        return 2
    bundle = resolve_bundle(args.policy)
    from policy.bundle import check_replan_every
    from runtime.pace import resolve_pace

    manifest = bundle_manifest(bundle)
    check_replan_every(args.replan_every, int(manifest["horizons"]["action"]))
    resolve_pace(manifest, args.speed)
    robot = {}
    for flag, given in (("--controller", args.controller), ("--limits", args.limits)):
        if given is not None and not (args.sim or args.robot_ip):
            print(f"sudd run: {flag} configures the robot node: add --sim or --robot-ip IP", file=sys.stderr)
            return 2
    # A bad file is a ConfigError naming the field, raised here before any node starts.
    from runtime.controller import ControllerConfig, load_controller, with_bundle_levels

    controller = load_controller(args.controller) if args.controller is not None else ControllerConfig()
    robot["controller"] = with_bundle_levels(controller, manifest)
    if args.limits is not None:
        from safety import load_limits

        load_limits(args.limits)  # checked against the arm's variant again by the robot node once it knows it
        robot["limits_file"] = str(args.limits.resolve())
    if args.sim:
        specs = sim_stack(str(bundle), task=args.task, seed=args.seed, dr=args.dr, replan_every=args.replan_every,
                          speed=args.speed, goal_query=not args.no_goal_query, phases=args.phases, **robot)
    elif args.robot_ip:
        serials = dict(s.split("=", 1) for s in args.camera_serial if "=" in s)
        specs = hardware_stack(str(bundle), args.robot_ip, serials, allow_motion=args.allow_motion,
                               replan_every=args.replan_every, speed=args.speed, goal_query=not args.no_goal_query,
                               phases=args.phases, **robot)
    else:
        specs = policy_stack(str(bundle), command=args.command or "", replan_every=args.replan_every,
                             speed=args.speed, goal_query=not args.no_goal_query, phases=args.phases)
    specs = [s for s in specs if node_kind(s) in kinds]
    la = Launcher(specs, hub=args.hub, robot_name=args.robot, connect=args.connect)
    succeeded = {"v": False}
    events: list = []
    t0 = time.monotonic()
    try:
        la.start()
    except NodeFailed as exc:
        print(f"sudd run: {exc}", file=sys.stderr)
        return 1
    with la:
        try:
            info = la.wait_ready()
        except NodeFailed as exc:
            print(f"sudd run: a node failed to start: {exc}", file=sys.stderr)
            return 1
        from runtime import bus as B
        from runtime.chunk_shaper import FIRST_WORDS

        shown = {"policy_phase", "policy_goal_point", "policy_look"} | {kind for _, _, kind, _ in FIRST_WORDS}

        def on_event(msg) -> None:
            events.append(msg)
            if msg.kind == "task_success":
                succeeded["v"] = True
            if msg.severity in ("warning", "error", "critical") or msg.kind.startswith(("command", "task")) \
                    or msg.kind in shown:
                print(f"[{msg.severity}] {msg.kind}: {msg.message}", file=sys.stderr)

        la.bus.subscribe(B.SAFETY_EVENT, on_event)
        command = args.command or info.get("robot", {}).get("instruction") or ""
        print(f"sudd run: ready in {time.monotonic() - t0:.1f} s; hub {la.hub}; "
              f"command: {command or '(none: use sudd say)'}", file=sys.stderr)
        answered = lambda: True  # noqa: E731
        if command and "policy" in kinds:
            la.say(command, "run")
        elif command:  # the policy node is elsewhere and may join later
            answered = la.say_until_answered(command, "run")
            print(f"sudd run: waiting for a policy node to join at {la.hub}", file=sys.stderr)
        done = (lambda: succeeded["v"]) if args.sim and "robot" in kinds else (lambda: False)
        reason = la.monitor(duration_s=args.duration, until=lambda: answered() and done())
    rob, pol = la.reports.get("robot", {}), la.reports.get("policy", {})
    lat = rob.get("latency_ms", {})
    summary = {"stop_reason": reason, "task_success": rob.get("task_success"), "at_rest": rob.get("at_rest"),
               "chunks": {"published": pol.get("chunks"), "received": rob.get("chunks_received"),
                          "accepted": rob.get("chunks_accepted"), "rejected": rob.get("chunks_rejected")},
               "latency_ms": {"obs_to_publish": lat.get("publish"), "obs_to_receive": lat.get("receive"),
                              "obs_to_accepted": lat.get("accepted"), "inference": pol.get("inference_ms")},
               "controller": {**{k: rob.get("controller_summary", {}).get(k)
                                 for k in ("rate_hz", "period_p99_ms", "jitter_p99_ms", "on_time")},
                              "latency_estimate_s": rob.get("latency_estimate_s")},
               "bypass": rob.get("bypass"), "exit_codes": la.exit_codes}
    if args.json:
        print(json.dumps({"summary": summary, "reports": la.reports}, indent=2, default=str))
    else:
        print(f"stop: {reason}")
        if "robot" in kinds:
            print(f"task success: {summary['task_success']}   arm at rest: {summary['at_rest']}")
        print(f"chunks: { {k: v for k, v in summary['chunks'].items() if v is not None} }")
        for k, v in summary["latency_ms"].items():
            if v and v.get("n"):
                print(f"latency {k:16s} p50 {v['p50']:.1f} ms  p99 {v['p99']:.1f} ms  (n={v['n']})")
        if "robot" in kinds:
            print(f"controller: {summary['controller']}")
    crashed = [n for n, c in la.exit_codes.items() if c not in (0, None)]
    return 1 if crashed else 0


def _say(args) -> int:
    from runtime import bus as B
    from runtime import messages as m
    from runtime.bus import Bus, BusConfig
    from runtime.bus_config import is_loopback
    from runtime.launch import answers
    from sim.config import ConfigError

    cid = uuid.uuid4().hex[:12]
    answer: list = []
    try:  # a hub on the robot's network (sudd run --hub tcp/0.0.0.0:7447) is as valid a target as loopback
        cfg = BusConfig(robot=args.robot, listen=(), connect=(args.connect,), loopback_only=is_loopback(args.connect))
    except ConfigError as exc:
        print(f"sudd say: {exc}", file=sys.stderr)
        return 2
    with Bus.open(cfg) as bus:
        if not bus.wait_for_peers(1, min(args.timeout, 5.0)):
            print(f"sudd say: nothing answers at {args.connect} (is `sudd run` up?)", file=sys.stderr)
            return 2
        bus.subscribe(B.SAFETY_EVENT, lambda msg: answer.append(msg)
                      if answers(msg, cid) else None)
        pub = bus.publisher(B.LANGUAGE_COMMAND)
        pub.wait_matched(min(args.timeout, 5.0))
        pub.publish(m.LanguageCommand(text=args.text, command_id=cid))
        deadline = time.monotonic() + args.timeout
        while not answer and time.monotonic() < deadline:
            time.sleep(0.02)
    if not answer:
        print(f"sent '{args.text}'; no answer from a policy node within {args.timeout} s")
        return 1
    ev = answer[0]
    print(f"{'ACCEPTED' if ev.kind == 'command_accepted' else 'REFUSED'}: {ev.message[len(cid) + 3:]}")
    return 0 if ev.kind == "command_accepted" else 3


__all__ = ["register", "resolve_bundle"]
