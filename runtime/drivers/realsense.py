"""RealSenseCamera: a RealSense D4xx (D435) as a `CameraDriver`, through pyrealsense2.

Why it looks like this:

* Same semantics as the twin (`sim/twins/camera.py`): colour RGB uint8, depth uint16 mm aligned to colour
  (`rs.align(color)`), `read` blocks for a frame newer than the last one returned, `read_latest` raises
  `StaleFrameError`, `capture_ns` is on the host's `time.monotonic_ns()` clock, `seq` strictly increases.
* A background thread drains the pipeline (librealsense's own frame queue + syncer) and keeps only the
  newest frames, so the control loop never waits on USB and never sees a backlog of old frames.
* The device source is injectable (`context=`: anything with `query_devices()`), so tests drive this exact
  code (serial selection, pipeline, syncer, align, timestamp mapping) with `SoftwareD435`, a camera built
  from librealsense's `software_device` with frames injected through `on_video_frame`.
* pyrealsense2 is imported lazily: importing this module is cheap and works where it is not installed.

Timestamps. librealsense stamps each frame in one of three domains (`frame.get_frame_timestamp_domain()`):
`global_time` (device clock mapped by librealsense onto the host clock, enabled here where supported) and
`system_time` (host time at arrival) are milliseconds of the host *wall* clock (librealsense's time service
is std::chrono::system_clock); they are mapped to `monotonic_ns` by the wall->monotonic offset, measured
at start and re-measured every `clock_resync_s` (NTP may slew or step the wall clock). `hardware_clock`
(device ms, unrelated to the host) is mapped by the smallest (arrival - device time) seen over the last
frames: that is exact up to the minimum transport latency, hence global time is preferred. A mapped time
is never later than the frame's arrival on the host nor earlier than the previous frame's (+1 ns).
Intrinsics are the colour stream's pinhole parameters; its distortion model/coefficients (zero on most
D435 colour sensors) are not applied and are available from `distortion()`.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from sim.camera_model import Intrinsics
from sim.devices import Frame, StaleFrameError, check_scalar

HARDWARE_CLOCK, SYSTEM_TIME, GLOBAL_TIME = 0, 1, 2  # rs2_timestamp_domain values


def _rs():
    import pyrealsense2 as rs  # lazy: a heavy native module, absent on machines without cameras

    return rs


class CameraNotFoundError(RuntimeError):
    """No camera with the requested serial (or none at all, or several and no serial given)."""


@dataclass(frozen=True)
class RealSenseConfig:
    serial: str | None = None  # None: the only connected camera (an error if several are connected)
    name: str = "scene_cam"  # the Frame.camera_id
    width: int = 640
    height: int = 480
    fps: int = 30
    depth: bool = True  # stream z16 depth and align it to colour
    clock_resync_s: float = 1.0  # how often the wall->monotonic offset is re-measured

    def __post_init__(self):
        check_scalar("width", self.width, 1, 4096, "px")
        check_scalar("height", self.height, 1, 4096, "px")
        check_scalar("fps", self.fps, 1, 300, "Hz")
        check_scalar("clock_resync_s", self.clock_resync_s, 0.01, 3600.0, "s")


def select_device(devices, serial: str | None):
    """The device with `serial` (or the only one); CameraNotFoundError listing what is connected."""
    rs = _rs()
    found = [(d.get_info(rs.camera_info.serial_number), d) for d in devices]
    listing = ", ".join(f"{s} ({d.get_info(rs.camera_info.name)})" if d.supports(rs.camera_info.name) else s
                        for s, d in found) or "none"
    if not found:
        raise CameraNotFoundError("no RealSense camera connected (check the USB 3 cable and udev rules; "
                                  "`rs-enumerate-devices` lists what librealsense sees)")
    if serial is None:
        if len(found) > 1:
            raise CameraNotFoundError(f"{len(found)} RealSense cameras connected: {listing}; "
                                      "set RealSenseConfig.serial to choose one")
        return found[0][1]
    for s, d in found:
        if s == serial:
            return d
    raise CameraNotFoundError(f"no RealSense camera with serial {serial!r}; connected: {listing}")


class HostClock:
    """Maps librealsense frame timestamps (ms, in a timestamp domain) to host `time.monotonic_ns()`."""

    def __init__(self, resync_s: float = 1.0, window: int = 64):
        self.resync_ns = int(resync_s * 1e9)
        self._wall_offset = self._measure_wall_offset()
        self._measured_at = time.monotonic_ns()
        self._hw_offsets: collections.deque[int] = collections.deque(maxlen=window)
        self._last = 0

    @staticmethod
    def _measure_wall_offset() -> int:
        """monotonic - wall, from the tightest of a few bracketed readings."""
        best = None
        for _ in range(5):
            m0, w, m1 = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
            if best is None or m1 - m0 < best[0]:
                best = (m1 - m0, (m0 + m1) // 2 - w)
        return best[1]

    def to_monotonic(self, timestamp_ms: float, domain: int, arrival_ns: int) -> int:
        if domain in (SYSTEM_TIME, GLOBAL_TIME):
            if arrival_ns - self._measured_at > self.resync_ns:
                self._wall_offset, self._measured_at = self._measure_wall_offset(), arrival_ns
            t = int(round(timestamp_ms * 1e6)) + self._wall_offset
        else:  # device clock: offset = min over recent frames of (arrival - device time)
            dev_ns = int(round(timestamp_ms * 1e6))
            sample = arrival_ns - dev_ns
            if self._hw_offsets and abs(sample - min(self._hw_offsets)) > 1_000_000_000:
                self._hw_offsets.clear()  # the device clock jumped (reset or wrap): start over
            self._hw_offsets.append(sample)
            t = dev_ns + min(self._hw_offsets)
        t = max(min(t, arrival_ns), self._last + 1)
        self._last = t
        return t


class RealSenseCamera:
    """CameraDriver on a RealSense. `context`: device source with `query_devices()` (default: rs.context())."""

    def __init__(self, config: RealSenseConfig | None = None, context=None):
        self.config = config or RealSenseConfig()
        self.name = self.config.name
        self._context = context
        self._cond = threading.Condition()
        self._frames: collections.deque[Frame] = collections.deque(maxlen=4)
        self._last_read = 0
        self._started = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pipe = None
        self._intrinsics: Intrinsics | None = None
        self._distortion: tuple[str, tuple[float, ...]] | None = None
        self.serial: str | None = None
        self.error: BaseException | None = None
        self.dropped = 0  # framesets without colour (or without depth when depth is on)
        self._last_fn, self._seq_base, self._last_seq = None, 0, 0  # kept across restarts: seq only grows

    # -- CameraDriver ----------------------------------------------------------------------------------------
    def intrinsics(self, stream: str = "color") -> Intrinsics:
        if stream not in ("color", "depth"):
            raise ValueError(f"stream = {stream!r} is not allowed; expected 'color' or 'depth'")
        if self._intrinsics is None:
            raise RuntimeError(f"camera {self.name!r}: intrinsics are read from the device; call start() first")
        return self._intrinsics  # depth is aligned to colour

    def distortion(self) -> tuple[str, tuple[float, ...]]:
        """The colour stream's distortion model name and coefficients (not applied to images)."""
        self.intrinsics()
        return self._distortion

    def start(self) -> None:
        if self._started:
            return
        rs, cfg = _rs(), self.config
        ctx = self._context if self._context is not None else rs.context()
        device = select_device(list(ctx.query_devices()), cfg.serial)
        self.serial = device.get_info(rs.camera_info.serial_number)
        for sensor in device.query_sensors():  # global time: device clock mapped onto host time
            if sensor.supports(rs.option.global_time_enabled) and not sensor.is_option_read_only(
                    rs.option.global_time_enabled):
                sensor.set_option(rs.option.global_time_enabled, 1)
        # A pipeline on the context the device came from; set_device() pins it to that device object
        # (software devices are not listed by contexts, so enable_device(serial) alone would not find it).
        pipe = rs.pipeline(ctx) if isinstance(ctx, rs.context) else rs.pipeline()
        pipe.set_device(device)
        rs_cfg = rs.config()
        rs_cfg.enable_device(self.serial)
        rs_cfg.enable_stream(rs.stream.color, cfg.width, cfg.height, rs.format.rgb8, cfg.fps)
        if cfg.depth:
            rs_cfg.enable_stream(rs.stream.depth, cfg.width, cfg.height, rs.format.z16, cfg.fps)
        try:
            profile = pipe.start(rs_cfg)
        except RuntimeError as exc:
            raise RuntimeError(f"camera {self.name!r} (serial {self.serial}): cannot stream rgb8+z16 "
                               f"{cfg.width}x{cfg.height} @ {cfg.fps} Hz: {exc}") from exc
        k = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self._intrinsics = Intrinsics(k.width, k.height, float(k.fx), float(k.fy), float(k.ppx), float(k.ppy))
        self._distortion = (str(k.model).split(".")[-1], tuple(float(c) for c in k.coeffs))
        align = rs.align(rs.stream.color) if cfg.depth else None
        self._pipe, self.error, self._last_fn = pipe, None, None
        self._frames.clear()
        self._stop.clear()
        self._started = True
        self._thread = threading.Thread(target=self._run, args=(pipe, align, HostClock(cfg.clock_resync_s)),
                                        name=f"realsense-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._pipe is not None:
            self._pipe.stop()
            self._pipe = None

    def read(self, timeout_s: float = 1.0) -> Frame:
        check_scalar("timeout_s", timeout_s, 0.0, None, "s")
        self._require_started()
        with self._cond:
            ok = self._cond.wait_for(lambda: not self._started or self.error is not None
                                     or (self._frames and self._frames[-1].seq > self._last_read), timeout_s)
            self._raise_thread_error()
            if not ok or not self._started:
                raise TimeoutError(f"camera {self.name!r}: no new frame within {timeout_s} s")
            frame = self._frames[-1]
            self._last_read = frame.seq
            return frame

    def read_latest(self, max_age_s: float) -> Frame:
        check_scalar("max_age_s", max_age_s, 0.0, None, "s")
        self._require_started()
        now = time.monotonic_ns()
        with self._cond:
            self._raise_thread_error()
            frame = self._frames[-1] if self._frames else None
            if frame is None:
                raise StaleFrameError(f"camera {self.name!r} has delivered no frame yet")
            age = (now - frame.capture_ns) * 1e-9
            if age > max_age_s:
                raise StaleFrameError(f"camera {self.name!r}: newest frame is {age * 1e3:.1f} ms old, "
                                      f"more than max_age_s = {max_age_s * 1e3:.1f} ms")
            self._last_read = max(self._last_read, frame.seq)
            return frame

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    # -- internals -------------------------------------------------------------------------------------------
    def _require_started(self) -> None:
        if not self._started:
            raise RuntimeError(f"camera {self.name!r} is not started; call start() first")

    def _raise_thread_error(self) -> None:
        if self.error is not None:
            raise RuntimeError(f"camera {self.name!r} thread failed: {self.error!r}") from self.error

    def _run(self, pipe, align, clock: HostClock) -> None:
        try:
            while not self._stop.is_set():
                ok, frames = pipe.try_wait_for_frames(100)
                if not ok:
                    continue
                arrival = time.monotonic_ns()
                if align is not None:
                    frames = align.process(frames)
                color = frames.get_color_frame()
                depth = frames.get_depth_frame() if align is not None else None
                if not color or (align is not None and not depth):
                    self.dropped += 1
                    continue
                fn = color.get_frame_number()
                if fn == self._last_fn:
                    continue  # the same colour frame again (re-emitted by the syncer)
                if fn + self._seq_base <= self._last_seq:  # the device restarted its frame counter
                    self._seq_base = self._last_seq + 1 - fn
                self._last_fn, self._last_seq = fn, fn + self._seq_base
                capture = clock.to_monotonic(color.get_timestamp(), int(color.get_frame_timestamp_domain()), arrival)
                frame = Frame(color=np.array(color.get_data(), dtype=np.uint8, copy=True),
                              depth=None if depth is None else _depth_mm(depth),
                              intrinsics=self._intrinsics, camera_id=self.name, seq=self._last_seq, capture_ns=capture)
                with self._cond:
                    self._frames.append(frame)
                    self._cond.notify_all()
        except BaseException as exc:  # surfaced by read()/read_latest()
            self.error = exc
            with self._cond:
                self._cond.notify_all()


def _depth_mm(depth_frame) -> np.ndarray:
    """z16 in the device's depth units (1 mm by default on D4xx) as uint16 millimetres."""
    raw = np.asanyarray(depth_frame.get_data())
    units = depth_frame.get_units()
    if abs(units - 0.001) < 1e-7:
        return np.array(raw, dtype=np.uint16, copy=True)
    return np.clip(np.rint(raw * (units * 1000.0)), 0, 65535).astype(np.uint16)


class SoftwareD435:
    """A D435 stand-in made of librealsense's `software_device`, for tests and dry runs without a camera.

    Colour (rgb8) and depth (z16, 1 mm units) sensors with the given intrinsics and identity depth->colour
    extrinsics; `push()` injects one colour+depth pair through `on_video_frame`, so it reaches the driver
    through the real librealsense syncer, pipeline queue and align block; `feed()` pushes a synthetic scene
    at `fps` from a thread. Pass it as `RealSenseCamera(config, context=SoftwareD435(...))`.

    What it cannot exercise: USB enumeration (pyrealsense2 2.59 contexts do not list software devices even
    after `add_to(ctx)`, hence the `context=` injection and `pipeline.set_device`), the global-time option
    (software sensors lack it; frames carry whatever domain `push` gives), real depth->colour extrinsics and
    lens distortion (identity and zero here, so align only re-projects onto the same pixels), and USB stalls.
    Align itself works: it needs the depth sensor's `depth_units` option and the registered extrinsics.
    """

    def __init__(self, serial: str = "000000000435", intrinsics: Intrinsics | None = None, fps: int = 30):
        rs = _rs()
        k = intrinsics or Intrinsics(96, 72, 92.25, 92.25, 47.5, 35.5)  # D435 colour fov at 96x72
        self.serial, self.intrinsics, self.fps, self.frame_number = serial, k, fps, 0
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.serial_number, serial)
        self.device.register_info(rs.camera_info.name, "Intel RealSense D435 (software)")
        self._depth_sensor = self.device.add_sensor("Stereo Module")
        self._depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
        self._color_sensor = self.device.add_sensor("RGB Camera")
        self._depth = self._add(self._depth_sensor, rs.stream.depth, rs.format.z16, 2, uid=0)
        self._color = self._add(self._color_sensor, rs.stream.color, rs.format.rgb8, 3, uid=1)
        ext = rs.extrinsics()
        ext.rotation, ext.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
        self._depth.register_extrinsics_to(self._color, ext)
        self.device.create_matcher(rs.matchers.dlr_c)  # pair depth and colour by frame number, like a D4xx
        self._feeding = threading.Event()
        self._thread: threading.Thread | None = None

    def _add(self, sensor, stream, fmt, bpp: int, uid: int):
        rs, k = _rs(), self.intrinsics
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = k.width, k.height, k.fx, k.fy, k.cx, k.cy
        intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.fmt, vs.bpp, vs.fps = stream, 0, uid, fmt, bpp, self.fps
        vs.width, vs.height, vs.intrinsics = k.width, k.height, intr
        return sensor.add_video_stream(vs).as_video_stream_profile()

    def query_devices(self) -> list:
        return [self.device]

    def push(self, color: np.ndarray, depth_mm: np.ndarray, timestamp_ms: float | None = None,
             domain: int = SYSTEM_TIME, frame_number: int | None = None) -> int:
        """Inject one frame pair (default stamp: now on the host wall clock). Returns its frame number."""
        rs = _rs()
        self.frame_number = self.frame_number + 1 if frame_number is None else frame_number
        ts = time.time() * 1000.0 if timestamp_ms is None else timestamp_ms
        for sensor, profile, pixels in ((self._depth_sensor, self._depth, np.ascontiguousarray(depth_mm, np.uint16)),
                                        (self._color_sensor, self._color, np.ascontiguousarray(color, np.uint8))):
            f = rs.software_video_frame()
            bpp = 2 if pixels.dtype == np.uint16 else 3
            f.pixels, f.bpp, f.stride, f.profile = pixels, bpp, self.intrinsics.width * bpp, profile
            f.timestamp, f.domain, f.frame_number = ts, rs.timestamp_domain(domain), self.frame_number
            if bpp == 2:
                f.depth_units = 0.001
            sensor.on_video_frame(f)
        return self.frame_number

    def scene(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """A synthetic frame pair: a moving colour gradient and a tilted plane 0.6-0.9 m away."""
        h, w = self.intrinsics.height, self.intrinsics.width
        y, x = np.mgrid[0:h, 0:w]
        color = np.stack([(x * 255 // max(w - 1, 1) + n) % 256, y * 255 // max(h - 1, 1),
                          np.full_like(x, (37 * n) % 256)], axis=-1).astype(np.uint8)
        depth = (600 + 300 * y // max(h - 1, 1)).astype(np.uint16)
        return color, depth

    def feed(self) -> "SoftwareD435":
        """Push `scene()` frames at `fps` from a thread until `stop_feed()`."""
        def run():
            period, t = 1.0 / self.fps, time.monotonic()
            while self._feeding.is_set():
                self.push(*self.scene(self.frame_number + 1))
                t += period
                time.sleep(max(0.0, t - time.monotonic()))
        self._feeding.set()
        self._thread = threading.Thread(target=run, name=f"software-d435-{self.serial}", daemon=True)
        self._thread.start()
        return self

    def stop_feed(self) -> None:
        self._feeding.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
