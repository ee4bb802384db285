"""sim_render: the sim cameras of `sudd run --sim`, rendered in their own process (off the robot node's GIL).

The robot node starts this process (`SimRenderProcess`) with the episode's (task, seed, dr); it builds the
same episode world (`build_episode(task, seed, dr, "fast", holdout)`: a bit-identical model, checked by a digest
at start-up), then waits for physics snapshots. The robot node's snapshot thread copies the rig's state at
the camera rate (`mj_getState(..., mjSTATE_INTEGRATION)` under the rig lock, a few microseconds) and sends it
with its time (the rig's `sample_ns`: the monotonic time of that physics state, as SimCamera stamps it)
through a Pipe. This process sets it (`mj_setState` + `mj_forward`), renders every camera with one
CameraRenderer (colour only, no shadows, as the in-process SimCamera with CameraNoiseConfig(shadows=False)),
applies the episode's sensor DR (colour gain and pixel noise: the parameters its recorded frames and the
lockstep eval's have for that seed, so a live seed K shows the policy what `sudd eval` seed K does) and
publishes CameraFrame messages itself, with capture time = the snapshot's time. When it falls behind it
renders only the newest snapshot (a camera with a full queue drops frames).

Protocol on the duplex Pipe: child -> parent `("ready", {...})` once, then `("report", {...})` at exit;
parent -> child snapshot bytes (`HEADER` + float64 state) or `STOP`. The child also exits when the pipe
breaks or its parent dies, and ignores SIGINT (the launcher decides the shutdown order).
"""

from __future__ import annotations

import hashlib
import logging
import os
import signal
import struct
import threading
import time
import types

import numpy as np

log = logging.getLogger(__name__)

HEADER = struct.Struct("<qq")  # snapshot seq, capture_ns (monotonic)
STOP = b"stop"


def state_spec():
    import mujoco

    return mujoco.mjtState.mjSTATE_INTEGRATION


def model_digest(model) -> str:
    """A digest of what makes two models render and integrate the same (sizes and the randomised fields)."""
    h = hashlib.sha256()
    h.update(np.array([model.nq, model.nv, model.na, model.nu, model.nmocap, model.nbody, model.ngeom,
                       model.ncam, model.nlight, model.nmat, model.neq], dtype=np.int64).tobytes())
    for name in ("qpos0", "body_pos", "body_quat", "body_mass", "geom_pos", "geom_quat", "geom_size", "geom_rgba",
                 "geom_friction", "mat_rgba", "cam_pos", "cam_quat", "cam_fovy", "light_pos", "light_dir",
                 "light_diffuse", "opt.timestep"):
        obj = model
        for part in name.split("."):
            obj = getattr(obj, part)
        h.update(np.ascontiguousarray(obj, dtype=np.float64).tobytes())
    return h.hexdigest()


def _build(task: str, seed: int, dr: str, holdout: dict):
    from sim.build import build_episode
    from sim.tasks import Holdout

    return build_episode(task, seed, dr, "fast", holdout=Holdout(colors=tuple(holdout.get("colors", ())),
                                                                    shapes=tuple(holdout.get("shapes", ())),
                                                                    split=holdout.get("split", "train")))


def serve(cfg: dict, conn) -> None:
    """Process target (spawn). cfg: bus (BusSettings as a dict), task, seed, dr, cameras {bus name: MuJoCo
    camera}, image_size (H, W)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Mesa's llvmpipe (software GL, no GPU here) rasterises on one thread per core by default: at 128x128 that
    # only makes each render a burst on every core at once, starving the robot node's 500 Hz loop.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    logging.basicConfig(level=os.environ.get("SUDD_LOG", "WARNING"),
                        format="%(asctime)s sim_render %(levelname)s %(name)s: %(message)s")
    report: dict = {"ok": False, "frames_published": {}, "snapshots": 0, "renders": 0, "dropped": 0,
                    "render_ms": {}}
    renderer = bus = None
    parent = os.getppid()
    try:
        import mujoco

        from runtime import bus as B
        from runtime import messages as m
        from runtime.nodes.common import BusSettings, config_from_dict, percentiles
        from sim.randomize import corrupt_image, episode_sensor_params
        from sim.render import CameraRenderer

        episode = _build(cfg["task"], int(cfg["seed"]), cfg["dr"], cfg.get("holdout", {}))
        model = episode.world.model
        data = mujoco.MjData(model)  # our own copy of the world, set from the snapshots
        spec = state_spec()
        nstate = mujoco.mj_stateSize(model, spec)
        H, W = (int(v) for v in cfg["image_size"])
        cams: dict[str, str] = dict(cfg["cameras"])
        renderer = CameraRenderer(types.SimpleNamespace(model=model, data=data), W, H, shadows=False)
        sensor = episode_sensor_params(episode)  # gain, pixel noise: as the seed's recorded and lockstep frames
        intr = {name: renderer.intrinsics(mj) for name, mj in cams.items()}
        bus = config_from_dict(BusSettings, cfg["bus"]).open()
        pubs = {name: bus.publisher(B.camera_color(name)) for name in cams}
        report["frames_published"] = {name: 0 for name in cams}
        render_ns: list[int] = []
        conn.send(("ready", {"digest": model_digest(model), "nstate": int(nstate), "pid": os.getpid()}))
        state = np.empty(nstate, dtype=np.float64)
        while not stop.is_set():
            if not conn.poll(0.5):
                if os.getppid() != parent:
                    report["stop_reason"] = "parent died"
                    break
                continue
            msg = conn.recv_bytes()
            while msg != STOP and conn.poll(0):  # behind: keep only the newest snapshot
                report["dropped"] += 1
                report["snapshots"] += 1
                msg = conn.recv_bytes()
            if msg == STOP:
                report["stop_reason"] = "stop requested"
                break
            report["snapshots"] += 1
            seq, capture_ns = HEADER.unpack_from(msg)
            state[:] = np.frombuffer(msg, dtype=np.float64, offset=HEADER.size, count=nstate)
            t0 = time.monotonic_ns()
            mujoco.mj_setState(model, data, state, spec)
            mujoco.mj_forward(model, data)
            for name, mj in cams.items():
                color = corrupt_image(renderer.rgb(mj), sensor, episode.rngs.sensor)
                pubs[name].publish(m.CameraFrame(camera_id=name, intrinsics=intr[name], capture_ns=capture_ns,
                                                 color=np.ascontiguousarray(color), frame_seq=seq))
                report["frames_published"][name] += 1
            render_ns.append(time.monotonic_ns() - t0)
            report["renders"] += 1
        report["render_ms"] = percentiles(render_ns[-2000:], 1e-6)
        report["ok"] = True
    except (EOFError, BrokenPipeError, ConnectionResetError):
        report["stop_reason"] = "pipe closed"
        report["ok"] = True
    except BaseException as exc:
        log.exception("sim_render failed")
        report["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if renderer is not None:
            try:
                renderer.close()
            except Exception:
                pass
        if bus is not None:
            try:
                bus.close()
            except Exception:
                pass
        try:
            conn.send(("report", report))
        except Exception:
            pass
        conn.close()


class SimRenderProcess:
    """Robot-node side: start the renderer process, check its world, feed it snapshots at the camera rate."""

    def __init__(self, bus_settings, task: str, seed: int, dr: str, cameras: dict[str, str],
                 image_size: tuple[int, int], fps: float, holdout=None):
        import multiprocessing as mp

        from runtime.nodes.common import config_to_dict

        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        cfg = {"bus": config_to_dict(bus_settings), "task": task, "seed": int(seed), "dr": dr,
               "cameras": dict(cameras), "image_size": list(image_size),
               "holdout": {"colors": list(holdout.colors), "shapes": list(holdout.shapes),
                           "split": holdout.split} if holdout else {}}
        self.proc = ctx.Process(target=serve, args=(cfg, child), name="sudd-sim-render", daemon=True)
        self.proc.start()
        child.close()
        self.period_ns = int(round(1e9 / fps))
        self.cameras = list(cameras)
        self.ready_info: dict | None = None
        self.report: dict = {}
        self.sent = 0
        self.send_errors = 0
        self._send_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._quit = threading.Event()

    def wait_ready(self, model, timeout_s: float = 60.0) -> dict:
        """Block until the child built its world; raises if it died or its model differs from `model`."""
        import mujoco

        deadline = time.monotonic() + timeout_s
        while not self._conn.poll(0.1):
            if not self.proc.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"sim_render process {'died' if not self.proc.is_alive() else 'timed out'} "
                                   f"during start-up (exit code {self.proc.exitcode})")
        kind, info = self._conn.recv()
        if kind != "ready":
            raise RuntimeError(f"sim_render failed during start-up: {info.get('error', info)}")
        if info["digest"] != model_digest(model) or info["nstate"] != mujoco.mj_stateSize(model, state_spec()):
            raise RuntimeError("sim_render built a different model than the robot node's (same task/seed/dr?)")
        self.ready_info = info
        return info

    def start(self, rig, enabled: threading.Event) -> None:
        """Snapshot thread: every camera period copy the rig's state (lock held) and send it to the child."""
        import mujoco

        model, data = rig.world.model, rig.world.data
        spec = state_spec()
        buf = np.empty(mujoco.mj_stateSize(model, spec), dtype=np.float64)

        def run() -> None:
            seq = 0
            next_ns = time.monotonic_ns()
            while not self._quit.is_set():
                wait = (next_ns - time.monotonic_ns()) * 1e-9
                if wait > 0 and self._quit.wait(wait):
                    break
                next_ns += self.period_ns
                now = time.monotonic_ns()
                if next_ns <= now:  # fell behind: skip, do not burst
                    next_ns = now + self.period_ns
                if not enabled.is_set():
                    continue
                with rig.lock:
                    mujoco.mj_getState(model, data, buf, spec)
                    capture_ns = rig.sample_ns  # the monotonic time of this physics state
                seq += 1
                try:
                    with self._send_lock:
                        self._conn.send_bytes(HEADER.pack(seq, capture_ns) + buf.tobytes())
                    self.sent += 1
                except (OSError, ValueError):
                    self.send_errors += 1
                    if not self.proc.is_alive():
                        log.error("sim_render process died (exit code %s): no more camera frames", self.proc.exitcode)
                        return

        self._thread = threading.Thread(target=run, name="sim-render-snapshots", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 5.0) -> dict:
        """Stop the snapshots, ask the child to stop, collect its report; terminate it if it does not exit."""
        self._quit.set()
        if self._thread is not None:
            self._thread.join(2.0)
        try:
            with self._send_lock:
                self._conn.send_bytes(STOP)
        except (OSError, ValueError):
            pass
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                if self._conn.poll(0.1):
                    kind, payload = self._conn.recv()
                    if kind == "report":
                        self.report = payload
                        break
                elif not self.proc.is_alive():
                    break
        except (EOFError, OSError):
            pass
        self.proc.join(max(0.1, deadline - time.monotonic()))
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2.0)
        self._conn.close()
        self.report.update(snapshots_sent=self.sent, send_errors=self.send_errors, exitcode=self.proc.exitcode)
        return self.report
