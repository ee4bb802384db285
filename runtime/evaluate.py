"""One closed-loop evaluation episode: a policy bundle drives the sim arm through the runtime's controller.

    out = run_policy_episode(bundle, "pick_place", seed=100_000, dr="heavy")
    out.success, out.sim_seconds, out.inference_ms

Not a shortcut: every chunk goes through `runtime.controller.ControllerLoop` (latency-compensated
scheduling, blending, interpolation to the 500 Hz servo rate) and every servo command through
`safety.SafetyFilter`, into the `SimArm`/`SimGripper` twins of a lockstep `SimRig`, exactly the objects
`sudd run --sim` drives, under the same limits: the defaults with the episode's bins as keep-out boxes, as a
real cell declares its fixtures (runtime.sim_cell). What differs from `sudd run --sim` is only how time passes:

* Lockstep, so a run is repeatable and needs no spare cores: the sim does not advance while the policy
  thinks. To keep the policy's real lag, each inference's measured wall time (on this CPU) is then let pass
  in sim time before its chunk reaches the controller, and the chunk is stamped from its observation time,
  as the policy node stamps it.
* Observations come from `datagen.recorder.Recorder`: the renderer, image size, sensor corruption and
  proprioception of the training data, sampled at the policy rate. (`sudd run --sim` renders the twins'
  cameras at their own size and the policy node resizes them; the evaluation removes that variable.)

Success is the task's own predicate (the same one that labels the data), checked at every policy tick; the
episode ends at success, at the time budget (task.max_seconds x `time_limit_factor`: 1 by default, as
`sudd eval`; the collector keeps `sudd datagen`'s 2), or at a protective stop the controller could not avoid.
Every episode also says what the gripper held on the way and, when it failed, why (`failure`, see
`runtime.eval_progress`).
"""

from __future__ import annotations

import functools
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from policy.pace import check_speed
from runtime.chunk_shaper import ChunkShaper
from runtime.controller import ControllerConfig, ControllerLoop, with_bundle_levels
from runtime.free_pace import FreePace, ceiling_of
from runtime.messages import ActionChunk
from runtime.pace import action_period_ns
from runtime.shaping import Shaping
from runtime.sim_cell import cell_limits
from safety import SafetyFilter, default_limits
from sim.build import build_episode
from sim.tasks import Holdout


@dataclass
class EpisodeOutcome:
    task: str
    seed: int
    command: str
    instruction: str
    success: bool
    sim_seconds: float
    end: str  # success | timeout | protective_stop
    stop_reason: str = ""  # what the sim robot's protective stop saw (contact pair or force)
    stop_speed_cm_s: float | None = None  # the TCP's speed at a contact-force stop (an impact or a press)
    stop_fingers_closed: bool | None = None  # at a contact-force stop: closed (on a handle, an object or nothing)
    chunks: int = 0
    rejected_chunks: int = 0
    inference_ms: list[float] = field(default_factory=list)
    events: dict[str, int] = field(default_factory=dict)
    target: dict = field(default_factory=dict)  # the target object's colour and shape
    held: list[str] = field(default_factory=list)  # objects the gripper held at some tick, first first
    failure: str = ""  # why it failed, one of runtime.eval_progress.FAILURES ("" on success)
    closest_cm: float | None = None  # nearest the TCP came to the named object before holding it
    closes: list[dict] = field(default_factory=list)  # how each close before holding it missed (eval_progress)
    target_end: str = ""  # a failure that held the named object: where it ended (eval_progress.TARGET_ENDS)
    target_lets_go: int = 0  # times the gripper stopped holding the named object
    releases: list[dict] = field(default_factory=list)  # where it was at each let-go, off the goal (eval_progress)
    drawer_max: float | None = None  # the drawer's largest open fraction, 0-1 (None: no drawer; eval_progress)
    drawer_end: float | None = None  # and at the end
    grasp_cycles: int = 0  # holds let go by the end, as the policy was told them (policy.stage)
    speed: float = 1.0  # the pace the chunks were played at (policy.pace)
    pauses_served: int = 0  # chunks played from where they move, the arm having held their pause (served_pause)
    finger_waits: int = 0  # chunks replaced by a hold while the fingers still closed or opened (finger_wait)
    grasp_steers: int = 0  # chunks moved over the located object after a close on nothing (grasp_steer)
    release_holds: int = 0  # chunks whose opening far from the drop was held back (release_guard)
    handle_levels: int = 0  # chunks whose heights were kept while the fingers held a drawer's handle (handle_height)
    free_ticks: int = 0  # ticks played at speed 1 in free space, the family's pace being slower (free_pace)
    empty_opens: int = 0  # chunks asked open after the fingers stood shut on nothing (empty_close)
    coherent_picks: list[int] | None = None  # with samples > 1: ticks compared, and where not the first sample won
    goal_point: list[float] | None = None  # the goal query's release point, base frame [m] (policy.goal_query)
    look_seconds: float | None = None  # spent on the goal query's look, there and back (runtime.look)
    look_gave_up: bool | None = None  # the look pose never reached: the head's own release point
    turn_deg: float | None = None  # the turn query's last target yaw from the start's (policy.turn_query)
    object_points: list | None = None  # the object query's object and drop, base frame [m] (policy.object_query)
    phase: int | None = None  # with phases: the last one reached (runtime.phases; None: one command)
    phase_starts: list[float] = field(default_factory=list)  # with phases: the sim time [s] each one began
    retreats: list[float] = field(default_factory=list)  # with phases: seconds each retreat to the start took
    runs_as: str | None = None  # the family the command was run as (runtime.command_family; None: none known)

    def record(self) -> dict:
        out = asdict(self)
        ms = np.asarray(self.inference_ms) if self.inference_ms else np.zeros(1)
        out["inference_ms"] = {"p50": float(np.median(ms)), "p99": float(np.percentile(ms, 99)), "n": len(self.inference_ms)}
        return out


def run_policy_episode(bundle, task: str, seed: int, *, dr: str = "heavy", holdout: Holdout = Holdout(),
                       command: str | None = None, paraphrase: bool = False, replan_every: int = 1,
                       time_limit_factor: float = 1.0, latency_s: float | None = None,
                       controller: ControllerConfig | None = None, observer=None, speed: float = 1.0,
                       goal_query: bool = True, phases: list | None = None,
                       shaping: Shaping = Shaping(), runs_as: str | None = None,
                       trace=None) -> EpisodeOutcome:
    """Run one episode (see the module docstring). `command` overrides the episode's instruction;
    `paraphrase` replaces it by one of the family's unseen phrasings; `replan_every` policy ticks between
    inferences (1: every tick, as the policy node); `latency_s` fixes the simulated inference lag instead
    of measuring it; `observer(world, instance)` is called at every policy tick (traces, videos); `speed` the
    pace the arm follows the chunks at (runtime.pace: ticks and actions 1 / (control_hz x speed) apart, the
    observations still 1 / control_hz); `goal_query` False: the head's own release point, where the bundle's
    goal query would replace it (policy.goal_query), or the object query a long task's later points
    (policy.object_query); `phases` (runtime.phases) run the command as skills, the
    phase and its text and pace chosen by the grasp cycles so far (`speed` then unused); `shaping` which of the
    steps between the denoiser and the controller run, and the samples drawn per tick (runtime/chunk_shaper.py);
    `runs_as` the family the command is run as, for the queries and the chunk steps (None: `task`; "": none;
    `sudd eval` passes the one the policy node would judge it, runtime.command_family); `trace` a
    runtime.eval_trace.Trace to record every tick, chunk and event in."""
    from policy.coherence import sample_chunks
    from policy.goal_query import GoalQuery
    from policy.object_query import ObjectQuery
    from policy.turn_query import TurnQuery

    from datagen.recorder import Recorder
    from policy.stage import GRIPPER_COLUMN, GraspCycles
    from runtime.eval_progress import GraspProgress
    from runtime.look import Look
    from runtime.phases import Sequencer
    from sim.twins.rig import SimRig

    check_speed(speed)  # before anything is built
    ep = build_episode(task, seed, dr, "fast", holdout=holdout)
    family, inst = ep.task, ep.instance
    if paraphrase:
        command = _paraphrase(family, inst)
    text = command or ep.instruction
    runs_as = task if runs_as is None else runs_as
    emb = bundle.embed(text)
    sequencer = Sequencer(phases, bundle.embed, emb, text) if phases else None
    query = GoalQuery(bundle, text, runs_as, enabled=goal_query)
    objects = ObjectQuery(bundle, text, runs_as, enabled=goal_query)
    look = Look(query)
    turn = TurnQuery(bundle, text, runs_as, enabled=goal_query)
    shaper = ChunkShaper(turn, shaping)
    rng = np.random.default_rng([seed, 11])
    rig = SimRig(ep.world, "lockstep")
    rig.gripper.activate()  # as the robot node does at start-up (a 2F-85 ignores commands until activated)
    limits = cell_limits(default_limits(ep.world.variant.name), ep.world)
    free = FreePace(ceiling_of(limits), shaping.free_pace)
    loop = ControllerLoop(rig.arm, rig.gripper, SafetyFilter(limits, collision=_guard(limits)),
                          with_bundle_levels(controller or ControllerConfig(), bundle.manifest))
    rec = Recorder(ep, image_size=tuple(bundle.image_size))
    control_hz = float(bundle.manifest["horizons"].get("control_hz", 10.0))
    dt_ns = action_period_ns(control_hz, speed)  # with phases, the first tick sets it to its phase's
    per_tick = max(1, round(dt_ns * 1e-9 / rig.control_period))
    To = bundle.obs_horizon
    budget = family.max_seconds * time_limit_factor
    target = _target_of(inst)
    out = EpisodeOutcome(task, int(seed), text, ep.instruction, False, 0.0, "timeout", target=target, speed=speed,
                         runs_as=runs_as or None)
    events: Counter = Counter()
    progress = GraspProgress()
    cycles = GraspCycles()  # grasp cycles since the start, as the policy node counts them
    try:
        rec.start()
        loop.cycle()  # the controller's first cycle: it now knows the arm's state
        rig.step(1)
        tick = 0
        while rig.world.time < budget:
            progress(rig.world, inst)
            for watch in (observer, trace):
                if watch is not None:
                    watch(rig.world, inst)
            if ep.success():
                out.success, out.end = True, "success"
                break
            if rig.protective_stopped:
                out.end, out.stop_reason = "protective_stop", str(rig.stop_reason or "")
                if rig.stop_tcp_speed is not None:
                    out.stop_speed_cm_s = round(100.0 * rig.stop_tcp_speed, 1)
                    out.stop_fingers_closed = bool(rig.world.gripper_command() >= 0.9)
                break
            t_obs = rig.now_ns()
            lag_cycles = 0
            if tick % replan_every == 0:
                images, proprio = rec.window(To)
                t0 = time.perf_counter()
                stage = cycles.update(rig.world.gripper_command(), proprio[-1, GRIPPER_COLUMN])
                shaper.regrasp.update(rig.world.gripper_command(), proprio[-1, GRIPPER_COLUMN], stage, rig.world.time)
                if sequencer is not None and sequencer.update(stage, proprio[-1]):  # the next skill: text, pace
                    out.phase, emb = sequencer.index, sequencer.embedding
                    out.phase_starts.append(round(float(rig.world.time), 2))
                # the skill's pace, or speed 1 while the hand is in free space (runtime/free_pace.py)
                dt_ns = action_period_ns(control_hz, free.speed(speed if sequencer is None else sequencer.speed,
                                                                float(proprio[-1, 2])))
                per_tick = max(1, round(dt_ns * 1e-9 / rig.control_period))
                n_exec = bundle.execute.stop - bundle.execute.start
                # the look's moves first: no query is asked of the frames on its way (they are not the start's)
                actions = look.chunk(images, proprio, rig.world.gripper_command(), n_exec, dt_ns * 1e-9)
                if actions is None:
                    release = query.release(images, proprio, stage)
                    given = {} if release is None else {"release": release}  # a policy without the query: none
                    given.update(objects.inputs(images, proprio, stage))
                    told = stage if sequencer is None else sequencer.stage(stage)
                    actions = None if sequencer is None else sequencer.retreat(
                        proprio[-1], rig.world.gripper_command(), proprio[-1, GRIPPER_COLUMN], n_exec, dt_ns * 1e-9)
                    if actions is None:  # the policy's turn (not a phase's retreat to the start)
                        chunks = sample_chunks(bundle, shaping.samples, images, proprio, emb, rng=rng, stage=told,
                                               **given)
                        actions = shaper.chunk(chunks[:, bundle.execute], images, proprio, stage, objects,
                                               rig.world.gripper_command(),
                                               runs_as if sequencer is None else sequencer.family, t_obs * 1e-9,
                                               dt_ns * 1e-9, speed=1e9 / (dt_ns * control_hz))
                    else:
                        shaper.forget()
                else:
                    shaper.forget()
                lag = time.perf_counter() - t0
                out.inference_ms.append(lag * 1e3)
                lag = lag if latency_s is None else latency_s
                lag_cycles = min(per_tick - 1, math.ceil(lag / rig.control_period))
                _run(loop, rig, lag_cycles, rec)
                times = (t_obs + dt_ns * (1 + np.arange(len(actions)))).astype(np.int64)
                ok = loop.submit(ActionChunk(actions=actions.astype(np.float64), times_ns=times, obs_time_ns=t_obs))
                if ok:  # its action times on the sim's clock, which the rig's started behind (the settling)
                    progress.plan(rig.world.time + (times - rig.now_ns()) * 1e-9, actions[:, :3])
                out.chunks += 1
                out.rejected_chunks += not ok
                if trace is not None:
                    trace.chunk(actions, ok)
            _run(loop, rig, per_tick - lag_cycles, rec)
            kinds = [e.kind for e in loop.drain_events()]
            events.update(kinds)
            if trace is not None:
                trace.events(kinds)
            tick += 1
        out.sim_seconds = round(float(rig.world.time), 3)
        out.grasp_cycles = cycles.count
        out.pauses_served = shaper.pause.trimmed
        out.finger_waits = shaper.wait.held
        out.grasp_steers = shaper.regrasp.steered
        out.release_holds = shaper.guard.held
        out.handle_levels = shaper.level.kept
        out.free_ticks = free.ticks
        out.empty_opens = shaper.empty.opened
        c = shaper.coherence
        out.coherent_picks = [c.chose, c.changed] if shaping.samples > 1 else None
        if sequencer is not None:
            out.retreats = sequencer.retreat_seconds
        if query.point is not None:
            out.goal_point = [round(float(v), 4) for v in query.point]
        if look.offset is not None:
            out.look_seconds = round(look.seconds, 2)
            out.look_gave_up = look.gave_up
        if turn.turn is not None:
            out.turn_deg = round(math.degrees(turn.turn), 1)
        if objects.points is not None:
            out.object_points = np.round(objects.points, 4).tolist()
        if not out.success:
            out.target_end = progress.target_end(inst)
        out.target_lets_go = progress.target_lets_go
    finally:
        rec.close()
        rig.close()
    out.events = dict(events)
    out.held = [inst.obj(n).phrase for n in progress.held]
    out.failure = progress.failure(out.success)
    out.closest_cm = None if progress.closest_m is None else round(100 * progress.closest_m, 1)
    out.closes = progress.closes
    out.releases = progress.releases
    if progress.drawer_max is not None:
        out.drawer_max, out.drawer_end = round(progress.drawer_max, 3), round(progress.drawer_end, 3)
    return out


def suite_holdout(suite: str, held: dict) -> Holdout:
    """The holdout a suite's scenes are built with: `held` {"colors", "shapes"} (what the bundle's data kept out)
    stay out of the scene; "heldout" makes the target one of them, "heldout_shape" a shape no data ever had
    (sim.tasks.base.NOVEL_SHAPES) in a colour the data had."""
    from sim.tasks.base import NOVEL_SHAPES

    colors, shapes = tuple(held.get("colors", ())), tuple(held.get("shapes", ()))
    if suite == "heldout_shape":
        return Holdout(colors=colors, shapes=tuple(dict.fromkeys(shapes + NOVEL_SHAPES)), split="eval_heldout_shape")
    return Holdout(colors=colors, shapes=shapes, split="eval_heldout" if suite == "heldout" else "train")


def episode_command(task: str, seed: int, dr: str = "heavy", holdout: Holdout = Holdout(),
                    paraphrase: bool = False) -> str:
    """The command `run_policy_episode(task, seed, ..., paraphrase=)` gives the policy, without building the world."""
    from sim.build import task_instance
    from sim.tasks import get_task

    family = get_task(task)
    inst = task_instance(family, seed, dr, holdout)
    return _paraphrase(family, inst) if paraphrase else inst.instruction


def _paraphrase(family, inst) -> str:
    return family.paraphrase(inst, np.random.default_rng([inst.seed, 7]))


@functools.lru_cache(maxsize=4)
def _guard(limits):
    """The safety filter's collision model for these limits (the keep-out boxes are this episode's bins),
    shared by episodes with the same cell: compiling it takes ~1 s, and it keeps no state between checks
    beyond scratch data."""
    from safety.collision import CollisionGuard

    return CollisionGuard(limits)


def _run(loop, rig, cycles: int, recorder=None) -> None:
    for _ in range(cycles):
        loop.cycle()
        rig.step(1)
        if recorder is not None:
            recorder(rig.world)


def _target_of(inst) -> dict:
    from runtime.eval_progress import target_name

    name = target_name(inst)
    if not name:
        return {}
    o = inst.obj(name)
    return {"color": o.color, "shape": o.shape}
