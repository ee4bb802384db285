"""policy_node: camera frames + robot state + the language command -> ActionChunks at the bundle's rate.

    python -m runtime.nodes.policy_node --config '{"bundle": "policy/bundles/multitask"}'

Runs in its own process, so inference (tens of ms) never blocks the 500 Hz controller. At most hz (the bundle's
control_hz, 10 Hz, times the command's speed; divided by `replan_every`) times a second, on the monotonic clock:

1. A tick is the arrival of a new frame of the first (primary) camera, at most hz a second, so
   inference starts as soon as the observation exists (the camera rate sets the pace; with no frames the
   node still wakes every 1/hz to notice staleness). Observation time t_obs = that frame's capture time.
   The To-step history is taken at t_obs - k / control_hz (k = To-1 .. 0), as trained: per camera
   the frame captured nearest each time, and the arm/gripper state whose timestamp is nearest (proprio:
   tcp position, rot6d, gripper, q, as datagen.schema records it).
2. Stale inputs (a camera with no frame captured within `max_frame_age_s`, or no robot state within
   `max_state_age_s`) => no chunk and one StatusEvent "policy_stale_input" (on the transition; "policy_resumed"
   when inputs are back). Without chunks the controller's plan runs out and its watchdog holds the arm.
3. No accepted command => no chunk (idle).
4. bundle.act (and the grasp cycles since the command was accepted, policy.stage, from the gripper's
   request and position at the newest step) -> the executed slice (bundle.execute) -> ActionChunk with
   times t_obs + (j + 1) / hz (the recorded action at step t is the target of step t + 1), obs_time_ns =
   t_obs. Aligning to the capture time (not the publish time) lets the controller drop what is already past
   and compensate its own latency.

Language: a LanguageCommand is compared with every trained instruction (bundle.task_similarity, MiniLM
cosine). Below `similarity_threshold` it is REFUSED: a StatusEvent "command_refused" names the closest
instruction, the cosine and the known tasks/instructions, and nothing is executed; a refused command also
clears the current one (the operator asked for something else: the arm holds rather than continuing an old
task). An accepted one gives "command_accepted", naming its family (that of the closest trained instruction)
and the speed that family plays at (policy.pace), which sets the ticks from then on. Both messages start with
"[command_id]" so `sudd say` can match its answer.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from runtime.nodes.common import BusSettings, NodeContext, cli_main, percentiles

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PolicyNodeConfig:
    bus: BusSettings = field(default_factory=BusSettings)
    bundle: str = ""
    similarity_threshold: float = 0.7  # cosine to the nearest trained instruction below this: refused
    max_frame_age_s: float = 0.35  # newest frame of any camera older than this: stale, no chunk
    max_state_age_s: float = 0.25  # the robot node publishes at 100 Hz; GIL stalls there reach ~0.1 s
    command: str = ""  # an initial command (as if received on the bus at start)
    threads: int = 1  # onnxruntime intra-op threads (2 shared cores: 1 leaves one for the controller)
    seed: int = 0
    # Infer on every Nth tick only (1..the bundle's action horizon): less CPU, the same action rate. The
    # chunk's actions stay 1/hz apart at the bundle's rate, the rate its demonstrations were recorded at.
    replan_every: int = 1
    # The pace the arm follows the chunks at, a fraction of the recorded one per task family (policy.pace):
    # "" the bundle's table; "F" every family at F; "TASK=F,..." those families. Ticks and actions
    # 1 / (hz x speed) apart; the observation history stays 1 / hz apart, as in training.
    speed: str = ""
    # Ask the head where the object a command puts something on is, for the families the bundle's manifest
    # lists (policy/goal_query.py), and a long task's later object where the bundle has an object query
    # (policy/object_query.py); false: the head's own points.
    goal_query: bool = True
    # Run a long command as the skills it is made of (runtime/phases.py; drawer_put: open the drawer, take the
    # object, close the drawer), switched by the grasp cycles, each at its family's pace. None: the families the
    # bundle's manifest lists (policy.phased); true: every family with phases; false: none.
    phases: bool | None = None
    # Play a chunk from where it moves once the arm has held still longer than any pause of the collector's
    # (runtime/served_pause.py); false: every chunk with its leading pause, to measure what this buys.
    served_pause: bool = True
    # Hold the arm where it is while the fingers still close or open as the chunk asks (runtime/finger_wait.py):
    # the collector's fingers shut in 0.1 s, the gripper's take 0.65 s; false: follow the chunks regardless.
    finger_wait: bool = True
    # After a close on nothing, move the policy's next approach over the object the object query located
    # (runtime/grasp_steer.py): the denoiser hardly follows the grasp point it is given; false: the policy's own.
    grasp_steer: bool = True
    # Hold back an opening on the object far from the object query's drop point, high above where the object lay, and
    # carry it there (runtime/release_guard.py): the policy now and then lets go in the air on the way; false: its own.
    release_guard: bool = True
    # Keep the height the fingers closed on a drawer's handle at while they hold it (runtime/handle_height.py): the
    # chunks sink as they pull or push, and the finger links press on the drawer's front; false: the policy's heights.
    handle_height: bool = True
    empty_close: bool = True  # open fingers shut on nothing for 1 s where they are (runtime/empty_close.py)
    free_pace: bool = True  # a slowed family at speed 1 in free space, high above the cell (runtime/free_pace.py)
    # That fixture's height [m, base frame]: the table or the highest keep-out box of the safety limits (the
    # launcher gives it from the sim cell or `--limits`); None: the cell is not known, no free pace.
    cell_ceiling_m: float | None = None
    # Chunks sampled per tick in one batch; the one that goes on most like the chunk before runs
    # (policy/coherence.py). 1: the plain sampler, one chunk from fresh noise at every tick.
    samples: int = 1


CONFIG = PolicyNodeConfig


def resize_nearest(img: np.ndarray, H: int, W: int) -> np.ndarray:
    """Centre-crop to the target aspect, then nearest-neighbour resize (a no-op at the right size)."""
    h, w = img.shape[:2]
    if (h, w) == (H, W):
        return img
    if h * W > w * H:  # too tall
        ch, cw = max(1, round(w * H / W)), w
    else:
        ch, cw = h, max(1, round(h * W / H))
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    ys = y0 + (np.arange(H) * ch // H)
    xs = x0 + (np.arange(W) * cw // W)
    return img[ys][:, xs]


def proprio_of(state, grip_pos: float) -> np.ndarray:
    """datagen.schema proprio (16,): tcp position 3, rot6d 6, gripper 1, q 6."""
    from datagen.schema import rot6d
    from sim.rotations import rotvec_to_matrix

    p = np.asarray(state.tcp_pose, dtype=float)
    return np.concatenate([p[:3], rot6d(rotvec_to_matrix(p[3:])), [grip_pos], np.asarray(state.q, float)])


class _History:
    """(time_ns, item) pairs in time order, bounded; nearest-by-time lookup."""

    def __init__(self, maxlen: int):
        self.t: deque = deque(maxlen=maxlen)
        self.v: deque = deque(maxlen=maxlen)
        self.lock = threading.Lock()

    def add(self, t: int, v) -> None:
        with self.lock:
            if self.t and t <= self.t[-1]:
                return  # duplicate or out of order: keep the history monotonic
            self.t.append(t)
            self.v.append(v)

    def newest(self):
        with self.lock:
            return (self.t[-1], self.v[-1]) if self.t else (None, None)

    def nearest(self, t: int):
        with self.lock:
            ts = list(self.t)
            if not ts:
                return None, None
            i = bisect.bisect_left(ts, t)
            cand = [j for j in (i - 1, i) if 0 <= j < len(ts)]
            j = min(cand, key=lambda j: abs(ts[j] - t))
            return ts[j], self.v[j]


def known_tasks_text(bundle) -> str:
    return (f"known tasks: {', '.join(bundle.tasks) or '(none recorded)'}; trained instructions: "
            + "; ".join(f"'{t}'" for t in bundle.instructions[:12])
            + (f" (+{len(bundle.instructions) - 12} more)" if len(bundle.instructions) > 12 else ""))


def judge_command(bundle, text: str, threshold: float) -> tuple[bool, str | None, float]:
    """(accepted, closest trained instruction, cosine)."""
    best, cos = bundle.task_similarity(text)
    return (best is not None and cos >= threshold), best, cos


def run(cfg: PolicyNodeConfig, ctx: NodeContext) -> dict:
    from policy.bundle import Bundle
    from policy.goal_query import GoalQuery
    from policy.coherence import check_samples, sample_chunks
    from policy.object_query import ObjectQuery
    from policy.turn_query import TurnQuery
    from policy.stage import GRIPPER_COLUMN, GraspCycles
    from runtime import bus as B
    from runtime.look import Look
    from runtime.pace import action_period_ns, command_speed, resolve_pace
    from policy.phased import resolve_phased
    from runtime.phases import Sequencer, phases_for
    from runtime.chunk_shaper import ChunkShaper
    from runtime.free_pace import FreePace
    from runtime.shaping import shaping_of
    from runtime import messages as m

    if not cfg.bundle:
        raise ValueError("policy node: no bundle given")
    bundle = Bundle.load(cfg.bundle, intra_op_num_threads=cfg.threads)
    bundle.check_replan_every(cfg.replan_every)
    check_samples(cfg.samples)
    data_hz = float(bundle.manifest["horizons"].get("control_hz", 10.0))
    To, (H, W) = bundle.obs_horizon, bundle.image_size
    obs_dt_ns = int(round(1e9 / data_hz))  # the observation history's spacing: the training data's
    pace = resolve_pace(bundle.manifest, cfg.speed)
    phased = resolve_phased(bundle.phased, cfg.phases)
    dt_ns = action_period_ns(data_hz, pace.speed(None))  # between the chunk's actions, and the node's ticks
    hz = 1e9 / dt_ns
    rng = np.random.default_rng(cfg.seed)
    report: dict = {"chunks": 0, "ticks": 0, "stale_ticks": 0, "idle_ticks": 0, "refused": 0, "accepted": 0,
                    "errors": 0, "free_ticks": 0}
    infer_ms: deque = deque(maxlen=2000)
    obs_to_pub_ms: deque = deque(maxlen=2000)
    frames = {c: _History(64) for c in bundle.cameras}
    states, grips = _History(256), _History(256)
    commands: deque = deque(maxlen=8)
    bus = cfg.bus.open()
    try:
        pub_chunk, pub_event = bus.publisher(B.POLICY_CHUNK), bus.publisher(B.SAFETY_EVENT)

        def event(kind: str, severity: str, message: str, **values) -> None:
            try:
                pub_event.publish(m.StatusEvent(kind=kind, severity=severity, message=message[:1000],
                                                values={k: float(v) for k, v in values.items()}))
            except ValueError as exc:
                log.warning("event %s not published: %s", kind, exc)

        primary = bundle.cameras[0]
        new_frame = threading.Event()  # a new frame of the primary camera: the policy's tick

        def on_frame(msg: m.CameraFrame, cam: str) -> None:
            if msg.color is not None:
                frames[cam].add(msg.capture_ns, msg.color)
                if cam == primary:
                    new_frame.set()

        for c in bundle.cameras:
            bus.subscribe(B.camera_color(c), lambda msg, c=c: on_frame(msg, c))
        bus.subscribe(B.ARM_STATE, lambda msg: states.add(msg.timestamp_ns, msg))
        bus.subscribe(B.GRIPPER_STATE,
                      lambda msg: grips.add(msg.timestamp_ns, (float(msg.position), float(msg.target))))
        bus.subscribe(B.LANGUAGE_COMMAND, lambda msg: commands.append((msg.command_id, msg.text)))
        if cfg.command:
            commands.append(("initial", cfg.command))
        current: dict = {"text": None, "emb": None, "query": None, "objects": None, "phases": None, "look": None,
                         "turn": None, "pause": None, "wait": None}
        cycles = GraspCycles()
        stale_state = None
        ctx.ready({"bundle": str(cfg.bundle), "cameras": bundle.cameras, "hz": hz / cfg.replan_every,
                   "tasks": bundle.tasks, "instructions": len(bundle.instructions), "pace": pace.table,
                   "phased": list(phased)})
        last_infer = -1.0
        while not ctx.should_stop():
            got = new_frame.wait(1.0 / hz)
            new_frame.clear()
            if got and time.monotonic() - last_infer < 0.9 * cfg.replan_every / hz:
                # Camera faster than the policy: wait for a fresher frame rather than use this one late
                # (sleeping to the next tick and then inferring on it added up to a frame period of latency).
                continue
            while commands:
                cid, text = commands.popleft()
                ok, best, cos = judge_command(bundle, text, cfg.similarity_threshold)
                tag = f"[{cid}] " if cid else ""
                if ok:
                    report["accepted"] += 1
                    cycles.reset()  # a new task starts at its first grasp
                    task, speed = command_speed(pace, best)
                    current.update(text=text, emb=bundle.embed(text),
                                   query=GoalQuery(bundle, text, task, enabled=cfg.goal_query),
                                   objects=ObjectQuery(bundle, text, task, enabled=cfg.goal_query))
                    current["look"] = Look(current["query"])
                    current["task"], current["speed"] = task, speed
                    current["free"] = FreePace(cfg.cell_ceiling_m, cfg.free_pace)
                    current["shaper"] = ChunkShaper(TurnQuery(bundle, text, task, enabled=cfg.goal_query),
                                                    shaping_of(vars(cfg)))
                    phases = phases_for(task, pace, bundle.instructions, bundle.tasks) if task in phased else None
                    current["phases"] = Sequencer(phases, bundle.embed, current["emb"], text) if phases else None
                    dt_ns = action_period_ns(data_hz, speed)
                    hz = 1e9 / dt_ns
                    q = current["query"]
                    asked = f"; where to put it asked as '{q.swapped}'" if q.active else ""
                    line = current["free"].line  # said where a pace below 1 may play: the family's or a phase's
                    if line is not None and (speed < 1 or phases):
                        asked += f"; a slower pace plays at 1 above z {line:.2f} m (free space)"
                    event("command_accepted", "info", f"{tag}accepted '{text}' (closest trained instruction "
                                                      f"'{best}', cosine {cos:.2f}; {task or 'no known family'} "
                                                      f"at speed {speed:g}{asked})", cosine=cos, speed=speed)
                else:
                    report["refused"] += 1
                    current.update(text=None, emb=None, query=None, objects=None, phases=None, look=None)
                    why = ("the bundle records no trained instructions" if best is None else
                           f"closest trained instruction '{best}' has cosine {cos:.2f} < "
                           f"{cfg.similarity_threshold:.2f}")
                    event("command_refused", "warning", f"{tag}refused '{text}': {why}; not executed. "
                                                        f"{known_tasks_text(bundle)}",
                          cosine=cos, threshold=cfg.similarity_threshold)
            report["ticks"] += 1
            now_ns = time.monotonic_ns()
            newest = {c: h.newest()[0] for c, h in frames.items()}
            st_t, st = states.newest()
            problem = None
            missing = [c for c, t in newest.items() if t is None or now_ns - t > cfg.max_frame_age_s * 1e9]
            if missing:
                problem = f"no frame newer than {cfg.max_frame_age_s:.2f} s from camera(s) {', '.join(missing)}"
            elif st_t is None or now_ns - st_t > cfg.max_state_age_s * 1e9:
                problem = f"no robot state newer than {cfg.max_state_age_s:.2f} s"
            if problem != stale_state:
                if problem and not ctx.winding_down():  # a shutdown stops the robot node first: no fault
                    event("policy_stale_input", "warning", f"{problem}: no chunks until inputs are fresh "
                                                           "(the controller holds)")
                elif not problem and stale_state is not None:
                    event("policy_resumed", "info", "inputs are fresh again")
                stale_state = problem
            if problem:
                report["stale_ticks"] += 1
            elif current["emb"] is None:
                report["idle_ticks"] += 1
            elif got:
                last_infer = time.monotonic()
                try:
                    t_obs = newest[primary]
                    times = [t_obs - (To - 1 - k) * obs_dt_ns for k in range(To)]
                    imgs = {c: np.stack([resize_nearest(frames[c].nearest(t)[1], H, W) for t in times])
                            for c in bundle.cameras}
                    prop = []
                    for t in times:
                        _, s = states.nearest(t)
                        _, g = grips.nearest(t)
                        prop.append(proprio_of(s, 0.0 if g is None else g[0]))
                    t0 = time.perf_counter()
                    # g: the newest step's (position, request), as training counts from the recorded steps
                    stage = cycles.update(0.0 if g is None else g[1], prop[-1][GRIPPER_COLUMN])
                    shaper = current["shaper"]
                    shaper.regrasp.update(0.0 if g is None else g[1], prop[-1][GRIPPER_COLUMN], stage, t_obs * 1e-9)
                    prop = np.asarray(prop, np.float32)
                    seq = current["phases"]
                    if seq is not None and seq.update(stage, prop[-1]):  # the next skill: its text, its pace
                        current["emb"] = seq.embedding
                        event("policy_phase", "info", seq.describe(current["text"]), phase=seq.index,
                              speed=seq.speed)
                    # the skill's pace, or speed 1 while the hand is in free space (runtime/free_pace.py)
                    dt_ns = action_period_ns(data_hz, current["free"].speed(
                        current["speed"] if seq is None else seq.speed, float(prop[-1][2])))
                    hz = 1e9 / dt_ns
                    report["free_ticks"] += current["free"].free
                    q, objects = current["query"], current["objects"]
                    settled, found = q.settled, len(objects.answers)
                    n_exec, request = bundle.execute.stop - bundle.execute.start, 0.0 if g is None else g[1]
                    look, looking = current["look"], current["look"].active
                    a = look.chunk(imgs, prop, request, n_exec, dt_ns * 1e-9)
                    if looking and not look.active:  # once per command that looks
                        event("policy_look", "warning" if look.gave_up else "info",
                              f"look pose {'never reached: the head answers' if look.gave_up else 'done'} after "
                              f"{look.seconds:.1f} s", seconds=look.seconds, gave_up=look.gave_up)
                    if a is None:  # past the look: no query is asked of the frames on its way
                        given = {"release": q.release(imgs, prop, stage), **objects.inputs(imgs, prop, stage)}
                        told = stage if seq is None else seq.stage(stage)  # a phase's own count (runtime.phases)
                        if seq is not None:
                            a = seq.retreat(prop[-1], request, prop[-1][GRIPPER_COLUMN], n_exec, dt_ns * 1e-9)
                        if a is None:  # the policy's turn (not a phase's retreat to the start)
                            a = sample_chunks(bundle, cfg.samples, imgs, prop, current["emb"], rng=rng, stage=told,
                                              **given)
                            turn, sure = shaper.turn, shaper.turn.sure
                            a = shaper.chunk(a[:, bundle.execute], imgs, prop, stage, objects, request,
                                             current["task"] if seq is None else seq.family, t_obs * 1e-9,
                                             dt_ns * 1e-9, speed=1e9 / (dt_ns * data_hz))
                            for kind, words in shaper.firsts:  # a step's first change to this command's chunks
                                event(kind, "info", words)
                            if turn.sure and not sure:  # the first sure answer, once per command
                                deg = float(np.degrees(turn.turn))
                                report["turn_deg"] = round(deg, 2)
                                event("policy_turn", "info", f"the wrist turns {deg:+.1f} deg to grasp square to "
                                      "the object's faces", turn_deg=deg)
                        else:  # a retreat's move: nothing of the policy's to go on from
                            shaper.forget()
                    else:  # the look's
                        shaper.forget()
                    if objects.active and found < objects.spec.ticks == len(objects.answers):  # once per command
                        report["object_points"] = np.round(objects.points, 4).tolist()
                        event("policy_object_points", "info", "the object at ({:.3f}, {:.3f}, {:.3f}) m, where it "
                              "goes ({:.3f}, {:.3f}, {:.3f}) m (base frame; given in grasp cycle {})".format(
                                  *objects.points.ravel(), objects.stage))
                    if q.settled and not settled:  # where the command's goal was found, once per command
                        report["goal_point"] = [round(float(v), 4) for v in q.point]
                        event("policy_goal_point", "info", "goal asked as '{}': at ({:.3f}, {:.3f}, {:.3f}) m in "
                              "the base frame".format(q.swapped, *q.point), x=q.point[0], y=q.point[1], z=q.point[2])
                    infer_ms.append((time.perf_counter() - t0) * 1e3)
                    tk = (t_obs + dt_ns * (1 + np.arange(len(a)))).astype(np.int64)
                    pub_chunk.publish(m.ActionChunk(actions=a.astype(np.float64), times_ns=tk, obs_time_ns=int(t_obs)))
                    obs_to_pub_ms.append((time.monotonic_ns() - t_obs) * 1e-6)
                    report["chunks"] += 1
                except Exception as exc:  # one bad observation must not end the node
                    report["errors"] += 1
                    log.exception("policy tick failed")
                    if report["errors"] <= 3:
                        event("policy_error", "error", f"inference failed: {exc!r}")
        report["stop_reason"] = ctx.stop_reason
        if current.get("shaper") is not None:  # the last command's: ticks compared with the chunk before, picks changed
            report["coherent_picks"] = [current["shaper"].coherence.chose, current["shaper"].coherence.changed]
    finally:
        report["inference_ms"] = percentiles(infer_ms)
        report["obs_to_publish_ms"] = percentiles(obs_to_pub_ms)
        bus.close()
    return report


def main(argv: list[str] | None = None) -> int:
    return cli_main(__name__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
