"""SimCamera: a RealSense twin (CameraDriver) rendering one MuJoCo camera: colour + aligned depth in mm.

Capture and delivery are separate, as on the real camera: a frame is *captured* (the physics state is
snapshotted and stamped with the rig clock) every 1/fps, and *delivered* `latency ± jitter` later; the
policy only ever sees delivered frames, so it meets the same staleness as on hardware. Rendering happens
from the snapshot into the camera's own MjData, never from the live physics data.

GL contexts belong to the thread that made them. In realtime mode one dedicated thread captures, renders and
delivers (its renderer is created there). In lockstep mode snapshots are taken inside the rig's control
cycle and rendered lazily, on demand, in the thread that reads them (which must then always be the same one).

Noise (all seeded per frame by (seed, seq), so lockstep runs repeat exactly): per-channel colour gain
jitter, gaussian pixel noise, gaussian depth noise; depth beyond `max_depth_m` reads 0 (no data).
"""

from __future__ import annotations

import collections
import math
import threading
import time
import types
from dataclasses import dataclass, field

import mujoco
import numpy as np

from sim.camera_model import Intrinsics
from sim.config import spec, validate
from sim.devices import Frame, StaleFrameError, check_scalar
from sim.render import CameraRenderer


@dataclass(frozen=True)
class CameraNoiseConfig:
    latency_s: float = field(default=0.0, metadata=spec(0.0, 1.0, "s", doc="capture to delivery"))
    jitter_s: float = field(default=0.0, metadata=spec(0.0, 0.5, "s", doc="uniform ± on the latency"))
    pixel_noise_std: float = field(default=0.0, metadata=spec(0.0, 64.0, "levels"))
    gain_jitter_std: float = field(default=0.0, metadata=spec(0.0, 0.5, doc="relative, per channel per frame"))
    depth_noise_std_mm: float = field(default=0.0, metadata=spec(0.0, 100.0, "mm"))
    max_depth_m: float = field(default=10.0, metadata=spec(0.1, 65.0, "m"))
    shadows: bool = True
    seed: int = 0


@dataclass
class _Snapshot:
    seq: int
    capture_ns: int
    deliver_ns: int
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    frame: Frame | None = None


class SimCamera:
    """CameraDriver twin; create it with `rig.camera(name, width, height, fps, noise)`."""

    def __init__(self, rig, name: str, width: int, height: int, fps: float, noise: CameraNoiseConfig | None = None):
        model = rig.world.model
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name) < 0:
            cams = [model.camera(i).name for i in range(model.ncam)]
            raise ValueError(f"no camera named {name!r} in the model; cameras: {cams}")
        gl = model.vis.global_
        check_scalar("width", width, 1, gl.offwidth, "px")
        check_scalar("height", height, 1, gl.offheight, "px")
        self.fps = check_scalar("fps", fps, 0.1, 1000.0, "Hz")
        self.noise = noise or CameraNoiseConfig()
        validate(self.noise)
        self.name, self._rig = name, rig
        self.width, self.height = int(width), int(height)
        self._period_ns = int(round(1e9 / self.fps))
        self._data = mujoco.MjData(model)  # the renderer's own copy of the world
        self._renderer: CameraRenderer | None = None
        self._render_thread: int | None = None
        self._cond = threading.Condition()
        self._frames: collections.deque[_Snapshot] = collections.deque(maxlen=8)
        self._seq = 0
        self._last_read = 0
        self._started = False
        self._next_capture_ns = 0
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        fovy = float(model.cam_fovy[model.camera(name).id])
        self._intrinsics = Intrinsics.from_fovy(self.width, self.height, fovy)

    def intrinsics(self, stream: str = "color") -> Intrinsics:
        if stream not in ("color", "depth"):
            raise ValueError(f"stream = {stream!r} is not allowed; expected 'color' or 'depth'")
        return self._intrinsics  # depth is rendered aligned to colour

    def start(self) -> None:
        with self._rig.lock:
            if self._started:
                return
            self._started = True
            self._next_capture_ns = self._rig.now_ns()
            if self._rig.mode == "lockstep":
                self._capture(self._next_capture_ns)  # the first frame at start, as a camera streams at once
            else:
                self._thread = threading.Thread(target=self._run, name=f"sim-camera-{self.name}", daemon=True)
                self._thread.start()

    def stop(self) -> None:
        with self._rig.lock:
            self._started = False
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        elif self._renderer is not None and self._render_thread == threading.get_ident():
            self._renderer.close()
            self._renderer = None

    def read(self, timeout_s: float = 1.0) -> Frame:
        check_scalar("timeout_s", timeout_s, 0.0, None, "s")
        self._require_started()
        if self._rig.mode == "lockstep":
            ok = self._rig.wait_until(lambda: self._newest_seq() > self._last_read, timeout_s)
            if not ok:
                raise TimeoutError(f"camera {self.name!r}: no new frame within {timeout_s} s")
            snap = self._newest(self._rig.now_ns())
            self._last_read = snap.seq
            return self._frame_of(snap)
        with self._cond:
            ok = self._cond.wait_for(lambda: not self._started or self.error is not None
                                     or (self._frames and self._frames[-1].seq > self._last_read), timeout_s)
            if self.error is not None:
                raise RuntimeError(f"camera {self.name!r} thread failed: {self.error!r}") from self.error
            if not ok or not self._started:
                raise TimeoutError(f"camera {self.name!r}: no new frame within {timeout_s} s")
            snap = self._frames[-1]
            self._last_read = snap.seq
            return snap.frame

    def read_latest(self, max_age_s: float) -> Frame:
        check_scalar("max_age_s", max_age_s, 0.0, None, "s")
        self._require_started()
        now = self._rig.now_ns()
        with self._cond:
            snap = self._newest(now) if self._rig.mode == "lockstep" else (self._frames[-1] if self._frames else None)
        if snap is None:
            raise StaleFrameError(f"camera {self.name!r} has delivered no frame yet")
        age = (now - snap.capture_ns) * 1e-9
        if age > max_age_s:
            raise StaleFrameError(f"camera {self.name!r}: newest frame is {age * 1e3:.1f} ms old, "
                                  f"more than max_age_s = {max_age_s * 1e3:.1f} ms")
        self._last_read = max(self._last_read, snap.seq)
        return self._frame_of(snap)

    # -- capture ---------------------------------------------------------------------------------------------
    def _require_started(self) -> None:
        if not self._started:
            raise RuntimeError(f"camera {self.name!r} is not started; call start() first")

    def _on_cycle(self, now_ns: int) -> None:
        """Called by the rig after each lockstep control cycle (lock held): capture when one is due."""
        if self._started and self._rig.mode == "lockstep" and now_ns >= self._next_capture_ns:
            self._capture(now_ns)

    def _capture(self, now_ns: int) -> _Snapshot:
        """Snapshot the physics state now (rig lock held) and schedule its delivery."""
        d = self._rig.world.data
        self._seq += 1
        rng = np.random.default_rng([self.noise.seed, self._seq, 0])
        delay = self.noise.latency_s + self.noise.jitter_s * rng.uniform(-1.0, 1.0)
        deliver = now_ns + max(0, int(delay * 1e9))
        if self._frames:
            deliver = max(deliver, self._frames[-1].deliver_ns)  # frames arrive in order
        snap = _Snapshot(self._seq, now_ns, deliver, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy())
        self._next_capture_ns += self._period_ns
        if self._next_capture_ns <= now_ns:  # fell behind: drop captures, like a camera with a full queue
            self._next_capture_ns = now_ns + self._period_ns
        if self._rig.mode == "lockstep":
            self._frames.append(snap)
        return snap

    def _newest(self, now_ns: int) -> _Snapshot | None:
        for snap in reversed(self._frames):
            if snap.deliver_ns <= now_ns:
                return snap
        return None

    def _newest_seq(self) -> int:
        snap = self._newest(self._rig.now_ns())
        return 0 if snap is None else snap.seq

    def _frame_of(self, snap: _Snapshot) -> Frame:
        if snap.frame is None:
            snap.frame = self._render(snap)
        return snap.frame

    def _render(self, snap: _Snapshot) -> Frame:
        if self._renderer is None:
            shim = types.SimpleNamespace(model=self._rig.world.model, data=self._data)
            self._renderer = CameraRenderer(shim, self.width, self.height, shadows=self.noise.shadows)
            self._render_thread = threading.get_ident()
        elif self._render_thread != threading.get_ident():
            raise RuntimeError(f"camera {self.name!r} must be read from the thread that first read it (GL context)")
        m, d = self._rig.world.model, self._data
        d.qpos[:], d.mocap_pos[:], d.mocap_quat[:] = snap.qpos, snap.mocap_pos, snap.mocap_quat
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        color = self._renderer.rgb(self.name)
        depth_m = self._renderer.depth(self.name)
        n = self.noise
        rng = np.random.default_rng([n.seed, snap.seq, 1])
        if n.gain_jitter_std > 0 or n.pixel_noise_std > 0:
            img = color.astype(np.float32) * (1.0 + n.gain_jitter_std * rng.standard_normal(3)).astype(np.float32)
            if n.pixel_noise_std > 0:
                img += n.pixel_noise_std * rng.standard_normal(img.shape, dtype=np.float32)
            color = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        valid = (depth_m > 0) & (depth_m < n.max_depth_m)
        if n.depth_noise_std_mm > 0:
            depth_m = depth_m + 1e-3 * n.depth_noise_std_mm * rng.standard_normal(depth_m.shape, dtype=np.float32)
        depth = np.where(valid, np.clip(np.rint(depth_m * 1000.0), 0, 65535), 0).astype(np.uint16)
        return Frame(color=np.ascontiguousarray(color), depth=depth, intrinsics=self._intrinsics, camera_id=self.name,
                     seq=snap.seq, capture_ns=snap.capture_ns)

    # -- realtime thread -------------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while self._started:
                wait = (self._next_capture_ns - time.monotonic_ns()) * 1e-9
                if wait > 0:
                    time.sleep(wait)
                with self._rig.lock:
                    if not self._started:
                        break
                    snap = self._capture(self._rig.sample_ns)  # the physics state's own time
                snap.frame = self._render(snap)
                wait = (snap.deliver_ns - time.monotonic_ns()) * 1e-9
                if wait > 0:
                    time.sleep(wait)
                with self._cond:
                    self._frames.append(snap)
                    self._cond.notify_all()
        except BaseException as exc:  # surfaced by read()
            self.error = exc
            with self._cond:
                self._cond.notify_all()
        finally:
            if self._renderer is not None:
                self._renderer.close()  # in the thread that owns the GL context
                self._renderer = None
