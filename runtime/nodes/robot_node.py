"""robot_node: the arm, the gripper and the chunk controller (500 Hz) behind the safety filter, on the bus.

    python -m runtime.nodes.robot_node --config '{"task": "pick_place", "seed": 0}'     # sim, foreground

Sim mode (`robot_ip` empty): build_episode(task, seed, dr, "fast") + SimRig(realtime) + ControllerLoop(
SimArm, SimGripper, SafetyFilter) + the sim cameras the policy needs (scene -> "scene_cam", wrist ->
"gripper/wrist_cam"), published as camera frames. The cameras render in their own process
(`runtime.nodes.sim_render`, `render_process=True`, the default): it builds the same episode world, gets a
physics snapshot (mj_getState) from this node at the camera rate and publishes the frames itself, so GL
rendering never holds this process's GIL against the 500 Hz loop; `render_process=False` renders them
here (SimCamera), as before. Hardware mode (`robot_ip` set): URRtdeArm + Robotiq2F85;
the cameras are the camera node's job. Without `allow_motion` the hardware node only connects, publishes
state and events and holds: no ControllerLoop, no servo_j, incoming chunks are counted and refused.

Threads in this process: the rig physics (sim), the controller loop (500 Hz, ControllerLoop.start()), the
snapshot sender for sim_render (or, with render_process=False, one renderer + one publisher per sim
camera), the chunk worker (IK of an incoming chunk, ~2 ms a knot, off the Zenoh thread and off the control
thread), and the main loop (~100 Hz): arm/gripper state, safety events, telemetry,
the task's success predicate (sim), fault injection (sim, for tests), parent watch.

Every servo_j goes through `GuardedArm`, which checks that the target it is given is exactly the safety
filter's latest output (`GuardedFilter` records it; both in `runtime.nodes.robot_guards`); a mismatch would
be a bypass and is counted (`report["bypass"]`, expected 0) and refused. Malformed chunk payloads are
dropped by the bus decoder (counted in `report["chunk_decode_errors"]`) and never reach
`ControllerLoop.submit`.

Stop (stop request, launcher death, or an exception): in `finally`, `ControllerLoop.stop()` (decelerate to
rest through the filter, then servo_stop), then cameras, rig and bus close; the report says whether the
arm was at rest.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from runtime.controller.config import ControllerConfig
from runtime.nodes.common import BusSettings, NodeContext, cli_main, percentiles
from runtime.nodes.robot_guards import GuardedArm, GuardedFilter, Hold
from runtime.nodes.sim_twin import frame_noises, note_sim_stop

log = logging.getLogger(__name__)

SIM_CAMERAS = {"scene": "scene_cam", "wrist": "gripper/wrist_cam"}  # bundle camera name -> MuJoCo camera


@dataclass(frozen=True)
class RobotNodeConfig:
    bus: BusSettings = field(default_factory=BusSettings)
    # sim
    task: str = "pick_place"
    seed: int = 0
    dr: str = "off"
    # Colours/shapes never made the target (sim.tasks.Holdout): the policy's training data kept them out
    # (`sudd datagen --holdout-color`), so `sudd run --sim --seed K` builds the scene `sudd eval` runs as seed K.
    holdout_colors: tuple[str, ...] = ()
    holdout_shapes: tuple[str, ...] = ()
    # "eval_heldout": the target only of them (`sudd eval --realtime --suite heldout`); "eval_heldout_shape": a ball
    holdout_split: str = "train"
    cameras: tuple[str, ...] = ("scene", "wrist")  # the bundle's camera names (sim cameras to publish)
    image_size: tuple[int, int] = (128, 128)  # (H, W) of the sim cameras
    camera_fps: float = 20.0  # twice the policy rate: the policy always finds a frame a few ms old
    render_process: bool = True  # sim cameras rendered in their own process (sim_render); False: in this one
    success_check_s: float = 0.5  # how often the task's success predicate is evaluated
    task_timeout_s: float = 0.0  # > 0: a "task_timeout" event after this long without success
    # hardware
    robot_ip: str = ""  # set: URRtdeArm + Robotiq2F85 instead of the sim
    gripper_port: int = 63352
    allow_motion: bool = False  # hardware: without it the node connects, reads state and holds (no servo)
    # both
    controller: ControllerConfig = field(default_factory=ControllerConfig)  # `sudd run --controller FILE.toml`
    limits_file: str = ""  # `sudd run --limits FILE.toml` (safety.load_limits); empty: default_limits(variant)
    state_hz: float = 100.0  # arm/gripper state publishing (downsampled from the control loop)
    telemetry_s: float = 1.0
    # fault injection (sim, tests): seconds after ready; 0 = off
    fault_protective_stop_s: float = 0.0
    fault_camera_stop_s: float = 0.0
    fault_camera_resume_s: float = 0.0  # > fault_camera_stop_s: the cameras come back then (fault clears)


CONFIG = RobotNodeConfig


def scene_holdout(cfg: RobotNodeConfig):
    """What the sim scene of this config keeps off its target (the bundle's held-out colours and shapes)."""
    from sim.tasks import Holdout

    return Holdout(colors=tuple(cfg.holdout_colors), shapes=tuple(cfg.holdout_shapes), split=cfg.holdout_split)


def run(cfg: RobotNodeConfig, ctx: NodeContext) -> dict:
    from runtime import bus as B
    from runtime import messages as m
    from runtime.controller import ControllerLoop
    from safety import SafetyFilter, load_limits

    report: dict = {"mode": "hardware" if cfg.robot_ip else "sim", "chunks_received": 0, "chunks_accepted": 0,
                    "chunks_rejected": 0, "frames_published": {}, "events": {}, "task_success": False}
    rig = episode = None
    noises: dict = {}  # sim cameras in this process: their sensor DR
    cams: dict = {}
    render = None  # sim_render.SimRenderProcess (render_process)
    bus = None
    loop = None
    threads: list[threading.Thread] = []
    quit_ = threading.Event()  # stops this node's helper threads
    cams_on = threading.Event()
    cams_on.set()
    arm = gripper = None
    q_start = chunk_sub = None
    chunk_lat: dict = {}
    try:
        bus = cfg.bus.open()
        # ---- devices -----------------------------------------------------------------------------------
        if cfg.robot_ip:
            from runtime.drivers.robotiq import Robotiq2F85, RobotiqConfig
            from runtime.drivers.ur_rtde_arm import URRtdeArm, URRtdeConfig

            raw_arm = URRtdeArm(URRtdeConfig(host=cfg.robot_ip))
            gripper = Robotiq2F85(RobotiqConfig(host=cfg.robot_ip, port=cfg.gripper_port))
            variant = "ur5e" if raw_arm.control_period <= 0.0021 else "ur5"
            if cfg.allow_motion:
                gripper.activate()
        else:
            from sim.build import build_episode
            from sim.twins.camera import CameraNoiseConfig
            from sim.twins.rig import SimRig

            for name in cfg.cameras:
                if name not in SIM_CAMERAS:
                    raise ValueError(f"camera {name!r}: the sim has {sorted(SIM_CAMERAS)}")
            if cfg.render_process and cfg.cameras:  # started first: it builds its world while we build ours
                from runtime.nodes.sim_render import SimRenderProcess

                render = SimRenderProcess(cfg.bus, cfg.task, cfg.seed, cfg.dr,
                                          {name: SIM_CAMERAS[name] for name in cfg.cameras}, cfg.image_size,
                                          cfg.camera_fps, holdout=scene_holdout(cfg))
            episode = build_episode(cfg.task, cfg.seed, cfg.dr, "fast", holdout=scene_holdout(cfg))
            rig = SimRig(episode.world, "realtime")
            raw_arm, gripper = rig.arm, rig.gripper
            variant = episode.world.variant.name
            H, W = cfg.image_size
            if render is None:
                for name in cfg.cameras:
                    cams[name] = rig.camera(SIM_CAMERAS[name], W, H, cfg.camera_fps,
                                            CameraNoiseConfig(shadows=False))
                noises = frame_noises(episode, cfg.seed, cfg.cameras)
            else:
                render.wait_ready(episode.world.model)
            rig.start()
            gripper.activate()
        limits = load_limits(cfg.limits_file or None, variant=variant)
        if episode is not None:  # the sim cell declares its fixtures (bins) as keep-out boxes
            from runtime.sim_cell import cell_limits

            limits = cell_limits(limits, episode.world)
        safety = GuardedFilter(SafetyFilter(limits))
        arm = GuardedArm(raw_arm, safety)
        if cfg.robot_ip and not cfg.allow_motion:
            loop = Hold()
        else:
            loop = ControllerLoop(arm, gripper, safety, cfg.controller)
        # ---- bus ---------------------------------------------------------------------------------------
        pub_state, pub_grip = bus.publisher(B.ARM_STATE), bus.publisher(B.GRIPPER_STATE)
        pub_event = bus.publisher(B.SAFETY_EVENT)
        pub_tel = bus.publisher(B.telemetry("controller"))
        chunk_lat = {"publish": deque(maxlen=2000), "receive": deque(maxlen=2000), "accepted": deque(maxlen=2000)}
        mailbox: list = [None]
        have_chunk = threading.Event()

        def on_chunk(msg: m.ActionChunk) -> None:  # Zenoh thread: stamp and hand over, nothing else
            recv = time.monotonic_ns()
            report["chunks_received"] += 1
            mailbox[0] = (msg, recv)
            have_chunk.set()

        def chunk_worker() -> None:
            while not quit_.is_set():
                if not have_chunk.wait(0.1):
                    continue
                have_chunk.clear()
                item, mailbox[0] = mailbox[0], None
                if item is None:
                    continue
                msg, recv = item
                ok = loop.submit(msg)
                done = time.monotonic_ns()
                report["chunks_accepted" if ok else "chunks_rejected"] += 1
                if ok:
                    chunk_lat["publish"].append(msg.stamp_ns - msg.obs_time_ns)
                    chunk_lat["receive"].append(recv - msg.obs_time_ns)
                    chunk_lat["accepted"].append(done - msg.obs_time_ns)

        def on_estop(msg: m.StatusEvent) -> None:
            loop.estop(f"bus e-stop: {msg.message or msg.kind}")

        chunk_sub = bus.subscribe(B.POLICY_CHUNK, on_chunk)
        bus.subscribe(B.ESTOP, on_estop)
        threads.append(threading.Thread(target=chunk_worker, name="chunk-worker", daemon=True))

        def camera_pub(name: str, cam) -> None:
            pub = bus.publisher(B.camera_color(name))
            report["frames_published"][name] = 0
            noise = noises.get(name)
            while not quit_.is_set():
                try:
                    f = cam.read(timeout_s=0.5)
                except TimeoutError:
                    continue
                if not cams_on.is_set():
                    continue
                pub.publish(m.CameraFrame(camera_id=name, intrinsics=f.intrinsics, capture_ns=f.capture_ns,
                                          color=f.color if noise is None else noise(f.color), frame_seq=f.seq))
                report["frames_published"][name] += 1

        for name, cam in cams.items():
            cam.start()
            threads.append(threading.Thread(target=camera_pub, args=(name, cam), name=f"pub-{name}", daemon=True))
        if render is not None:
            render.start(rig, cams_on)
        for t in threads:
            t.start()
        loop.start()
        deadline = time.monotonic() + 5.0
        while not getattr(loop, "ready", True) and time.monotonic() < deadline:
            time.sleep(0.005)

        def event(kind: str, severity: str = "info", message: str = "", **values) -> None:
            report["events"][kind] = report["events"].get(kind, 0) + 1
            try:
                pub_event.publish(m.StatusEvent(kind=kind, severity=severity, message=message[:1000],
                                                values={k: float(v) for k, v in values.items()}))
            except ValueError as exc:
                log.warning("event %s not published: %s", kind, exc)

        def flush_events() -> None:
            for ev in loop.drain_events():
                report["events"][ev.kind] = report["events"].get(ev.kind, 0) + 1
                try:
                    pub_event.publish(m.StatusEvent.from_safety_event(ev))
                except ValueError as exc:
                    log.warning("safety event %s not published: %s", ev.kind, exc)

        info = {"mode": report["mode"], "variant": variant,
                "cameras": list(cams) if render is None else list(render.cameras)}
        if episode is not None:
            info.update(task=cfg.task, seed=cfg.seed, instruction=episode.instruction)
        report["instruction"] = info.get("instruction")
        ctx.ready(info)
        event("robot_ready", message=f"robot node up ({report['mode']}, {variant})"
              + ("" if not cfg.robot_ip or cfg.allow_motion else "; motion NOT allowed: holding"))
        # ---- main loop ---------------------------------------------------------------------------------
        t0 = time.monotonic()
        period = 1.0 / cfg.state_hz
        next_t = t0
        next_check, next_tel = t0 + cfg.success_check_s, t0 + cfg.telemetry_s
        next_est = t0 + 5.0
        injected_ps = injected_cam = timed_out = False
        q_start = None
        stop_seen = None  # the sim stop already reported
        report["protective_stops"] = []
        while not ctx.should_stop():
            now = time.monotonic()
            s = arm.state()
            if q_start is None:
                q_start = np.array(s.q)
            pub_state.publish(m.RobotState.from_arm_state(s))
            pub_grip.publish(m.GripperStatus.from_gripper_state(gripper.state()))
            flush_events()
            if rig is not None:
                stop_seen = note_sim_stop(rig, stop_seen, now - t0, report, event)
            if episode is not None and now >= next_check and not report["task_success"]:
                next_check = now + cfg.success_check_s
                with rig.lock:
                    ok = episode.success()
                if ok:
                    report["task_success"] = True
                    report["success_after_s"] = now - t0
                    event("task_success", message=f"task done: {episode.instruction}", after_s=now - t0)
                elif cfg.task_timeout_s > 0 and now - t0 > cfg.task_timeout_s and not timed_out:
                    timed_out = True
                    event("task_timeout", "warning", f"no success within {cfg.task_timeout_s} s: "
                                                     f"{episode.instruction}", after_s=now - t0)
            if now >= next_tel:
                next_tel = now + cfg.telemetry_s
                summ = loop.telemetry.summary()
                tel = {k[:-3]: int(v * 1e6) for k, v in summ.items() if k.endswith("_ms") and np.isfinite(v)}
                if chunk_lat["receive"]:
                    tel["obs_to_controller_p50"] = int(np.percentile(chunk_lat["receive"], 50))
                if hasattr(loop, "latency_estimate") and now >= next_est:  # every 5 s: ~1 ms of numpy
                    next_est = now + 5.0
                    est = loop.latency_estimate()
                    if est is not None:  # the servo lag to set as execution_latency (sudd run --controller)
                        report["latency_estimate_s"] = round(float(est), 4)
                if "latency_estimate_s" in report:
                    tel["latency_estimate"] = int(report["latency_estimate_s"] * 1e9)
                if tel:
                    pub_tel.publish(m.Telemetry(durations_ns=tel))
            if rig is not None and cfg.fault_protective_stop_s > 0 and not injected_ps \
                    and now - t0 >= cfg.fault_protective_stop_s:
                injected_ps = True
                rig.trigger_protective_stop("injected fault (fault_protective_stop_s)")
                report["protective_stop_injected_at"] = now - t0
            if (cams or render is not None) and cfg.fault_camera_stop_s > 0 and not injected_cam \
                    and now - t0 >= cfg.fault_camera_stop_s:
                injected_cam = True
                cams_on.clear()
                report["camera_stopped_at"] = now - t0
            if injected_cam and not cams_on.is_set() and cfg.fault_camera_resume_s > cfg.fault_camera_stop_s \
                    and now - t0 >= cfg.fault_camera_resume_s:
                cams_on.set()
                report["camera_resumed_at"] = now - t0
            next_t += period
            if next_t < now:
                next_t = now + period
            ctx.sleep_until(next_t)
        report["stop_reason"] = ctx.stop_reason
    finally:
        # controlled stop FIRST (through the filter), then everything else
        if loop is not None:
            try:
                report["controller_summary"] = loop.telemetry.summary()
                report["at_rest"] = bool(loop.stop())
                report["controller_state"] = loop.state
            except Exception as exc:
                log.exception("controlled stop failed")
                report["at_rest"] = False
                report["stop_error"] = repr(exc)
            try:
                for ev in loop.drain_events():
                    report["events"][ev.kind] = report["events"].get(ev.kind, 0) + 1
            except Exception:
                pass
        if arm is not None:
            report["servo_sent"] = arm.servo_sent
            report["bypass"] = arm.bypass
            try:
                s = arm.state()
                report["final_qd_max"] = float(np.max(np.abs(s.qd)))
                if q_start is not None:
                    report["moved_rad"] = float(np.max(np.abs(np.asarray(s.q) - q_start)))
            except Exception:
                pass
        quit_.set()
        for t in threads:
            t.join(2.0)
        for cam in cams.values():
            try:
                cam.stop()
            except Exception:
                pass
        if render is not None:
            try:
                rr = render.close()
                report["frames_published"] = dict(rr.get("frames_published", {}))
                report["sim_render"] = {k: v for k, v in rr.items() if k != "frames_published"}
            except Exception as exc:
                log.exception("sim_render close failed")
                report["sim_render"] = {"error": repr(exc)}
        if rig is not None:
            if "protective_stops" in report:  # a stop in the controlled stop, after the main loop
                note_sim_stop(rig, stop_seen, time.monotonic() - t0, report, None)
            report["protective_stopped"] = rig.protective_stopped
            # physics behind the wall clock: the arm lags its targets, unlike a real UR's 500 Hz controller
            report["sim_physics"] = {"rate_hz": round(rig.achieved_rate_hz(), 1), "overruns": rig.overruns}
            rig.close()
        elif cfg.robot_ip:
            for dev, close in ((arm, "close"), (gripper, "disconnect")):
                try:
                    getattr(dev, close)()
                except Exception:
                    pass
        if bus is not None:
            if chunk_sub is not None:
                report["chunk_decode_errors"] = dict(chunk_sub.stats.decode_errors)
            report["latency_ms"] = {k: percentiles(v, 1e-6) for k, v in chunk_lat.items()}
            bus.close()
    return report


def main(argv: list[str] | None = None) -> int:
    return cli_main(__name__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
