"""SimRig: one simulated work cell (a World) with its clock, handing out the arm, gripper and camera twins.

Why a rig: the twins share one physics state and one clock, exactly as the real devices share the real
world and the host's monotonic clock. Two clock modes:

* `lockstep` (tests, data generation): time advances only inside `rig.step(n_cycles)` or inside a blocking
  call (move_j, gripper.move(wait=True), camera.read, arm.wait_period), so runs are bit-for-bit repeatable.
  Timestamps are the rig's cycle count times the control period, in ns.
* `realtime` (closed-loop rehearsal): a background thread runs one control cycle per control period
  against time.monotonic; timestamps are time.monotonic_ns(), as the real drivers report. All access to
  MuJoCo data goes through `rig.lock`.

One control cycle = controller updates (arm interpolator, gripper ramp) + the physics substeps of one
controller period + the protective-stop contact check after every physics step.

Protective stop (as the UR safety system): two robot parts colliding (arm link with arm link or with the
gripper; the gripper's own linkage is exempt), or any other robot contact pressing harder than
`force_limit_n`, be it on something welded to the world (table, floor, bins) or on a movable object (finger
pads on movable objects are exempt: that is a grasp). Like the real arm's force limit, a graze is not a
stop; a stiff position-controlled arm driven into the table builds the limit within millimetres. The arm
then holds the position it had, commands return False, and `unlock_protective_stop()` succeeds only
`unlock_delay_s` after the stop. Contacts present at unlock (or at start-up) are forgiven until they
separate, so the arm can be moved away. Note the scene's walls have no collision geometry (contype 0), so
they cannot trigger a stop.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from sim.config import spec, validate
from sim.devices import UNLOCK_DELAY_S
from sim.robot import ARM_BODIES, GRIPPER_PAD_GEOMS, GRIPPER_PREFIX
from sim.twins.arm import ArmNoiseConfig, SimArm
from sim.twins.camera import CameraNoiseConfig, SimCamera
from sim.twins.gripper import SimGripper
from sim.twins.wrench import tool_wrench

MODES = ("lockstep", "realtime")


@dataclass(frozen=True)
class ProtectiveStopConfig:
    enabled: bool = True
    force_limit_n: float = field(default=150.0, metadata=spec(1.0, 10000.0, "N", doc="robot contact force limit"))
    unlock_delay_s: float = field(default=UNLOCK_DELAY_S, metadata=spec(0.0, 60.0, "s"))


class SimRig:
    """The world, its clock and the device twins. Use as a context manager or call `close()`."""

    def __init__(self, world, mode: str = "lockstep", *, arm_noise: ArmNoiseConfig | None = None,
                 safety: ProtectiveStopConfig | None = None):
        if mode not in MODES:
            raise ValueError(f"mode = {mode!r} is not allowed; expected one of {list(MODES)}")
        self.world, self.mode = world, mode
        self.safety = safety or ProtectiveStopConfig()
        validate(self.safety)
        self.control_period = float(world.variant.control_period)
        self.substeps = max(1, round(self.control_period / world.timestep))
        self._period_ns = int(round(self.control_period * 1e9))
        self.lock = threading.RLock()
        self._cond = threading.Condition(self.lock)
        self.cycles = 0
        self.sample_ns = self.now_ns()  # rig time of the latest physics state (what state() stamps)
        self.error: BaseException | None = None
        self.stop_reason: str | None = None
        self.stop_tcp_speed: float | None = None  # m/s at a contact-force stop: an impact or a press
        self._stop_ns: int | None = None
        self._grace: set[tuple[int, int]] = set()
        self._classify_geoms()
        # Contacts present at start-up are forgiven until they separate, as after an unlock (the robot
        # was placed that way; e.g. the UR5 variant's shoulder capsule rests in the table top).
        self._grace = self._present_contacts()
        self._cameras: list[SimCamera] = []
        self._thread: threading.Thread | None = None
        self._running = False
        self._rt_start_ns = 0
        self._rt_cycles = 0
        self.overruns = 0
        self.arm = SimArm(self, arm_noise)
        self.gripper = SimGripper(self)

    # -- clock -----------------------------------------------------------------------------------------
    def now_ns(self) -> int:
        if self.mode == "lockstep":
            return self.cycles * self._period_ns
        return time.monotonic_ns()

    def step(self, n_cycles: int = 1) -> None:
        """Advance `n_cycles` control cycles (lockstep only)."""
        if self.mode != "lockstep":
            raise RuntimeError("rig.step() is for lockstep mode; in realtime mode the rig's thread steps physics")
        with self.lock:
            for _ in range(int(n_cycles)):
                self._cycle()

    def sleep(self, seconds: float) -> None:
        """Let `seconds` of rig time pass (lockstep: step; realtime: wall-clock sleep)."""
        if self.mode == "lockstep":
            self.step(max(0, math.ceil(seconds / self.control_period - 1e-9)))
        else:
            time.sleep(max(0.0, seconds))

    def wait_until(self, predicate, timeout_s: float) -> bool:
        """Block until `predicate()` (evaluated under the lock) holds; False on timeout (rig time)."""
        if self.mode == "lockstep":
            with self.lock:
                for _ in range(max(1, math.ceil(timeout_s / self.control_period))):
                    if predicate():
                        return True
                    self._cycle()
                return bool(predicate())
        if not self.running:
            raise RuntimeError("the realtime rig is not running; call rig.start() (or use it as a context manager)")
        with self._cond:
            ok = self._cond.wait_for(lambda: predicate() or self.error is not None or not self._running, timeout_s)
            self._raise_if_failed()
            return bool(ok and predicate())

    # -- realtime ------------------------------------------------------------------------------------
    def start(self) -> "SimRig":
        """Start the physics thread (realtime); a no-op in lockstep."""
        if self.mode == "realtime" and self._thread is None:
            self._running = True
            self._thread = threading.Thread(target=self._run, name="sim-rig-physics", daemon=True)
            self._thread.start()
        return self

    def achieved_rate_hz(self) -> float:
        """Control cycles per wall-clock second since `start()` (realtime)."""
        elapsed = (time.monotonic_ns() - self._rt_start_ns) * 1e-9
        return self._rt_cycles / elapsed if self._rt_cycles and elapsed > 0 else 0.0

    def _run(self) -> None:
        self._rt_start_ns = deadline = time.monotonic_ns()
        try:
            while self._running:
                with self._cond:
                    self._cycle()
                self._rt_cycles += 1
                deadline += self._period_ns
                lag = time.monotonic_ns() - deadline
                if lag < 0:
                    time.sleep(-lag * 1e-9)
                elif lag > 25 * self._period_ns:  # far behind (GC pause, loaded CPU): skip, do not burst
                    self.overruns += 1
                    deadline = time.monotonic_ns()
        except BaseException as exc:  # surfaced to every blocking caller
            self.error = exc
        finally:
            with self._cond:
                self._running = False
                self._cond.notify_all()

    def _raise_if_failed(self) -> None:
        if self.error is not None:
            raise RuntimeError(f"the sim rig's physics thread failed: {self.error!r}") from self.error

    def close(self) -> None:
        for cam in list(self._cameras):
            cam.stop()
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                raise RuntimeError("the sim rig's physics thread did not stop within 2 s")
            self._thread = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- devices -----------------------------------------------------------------------------------------
    def camera(self, name: str, width: int = 640, height: int = 480, fps: float = 30.0,
               noise: CameraNoiseConfig | None = None) -> SimCamera:
        """A camera twin for the MuJoCo camera `name` (e.g. "scene_cam", "gripper/wrist_cam")."""
        cam = SimCamera(self, name, width, height, fps, noise)
        self._cameras.append(cam)
        return cam

    # -- one control cycle (lock held) ---------------------------------------------------------------
    def _cycle(self) -> None:
        dt = self.control_period
        self.arm._update(dt)
        self.gripper._update(dt)
        for _ in range(self.substeps):
            self.world.step(1)
            if self.safety.enabled and self._stop_ns is None:
                self._check_contacts()
        self.cycles += 1
        self.sample_ns = now = self.now_ns()
        for cam in self._cameras:
            cam._on_cycle(now)
        self._cond.notify_all()

    # -- protective stop ---------------------------------------------------------------------------------
    @property
    def protective_stopped(self) -> bool:
        return self._stop_ns is not None

    def trigger_protective_stop(self, reason: str = "injected fault", tcp_speed: float | None = None) -> None:
        """Fault injection: stop as if the safety system had tripped."""
        with self.lock:
            if self._stop_ns is None:
                self._stop_ns, self.stop_reason, self.stop_tcp_speed = self.now_ns(), reason, tcp_speed
                self.arm._freeze()

    def reset(self) -> None:
        """Back to the world's initial state with no stop latched, as after a controller power cycle."""
        with self.lock:
            self._stop_ns, self.stop_reason, self.stop_tcp_speed = None, None, None
            self.world.reset()
            self.arm._freeze()
            self._grace = self._present_contacts()

    def _unlock(self) -> bool:
        with self.lock:
            if self._stop_ns is None:
                return True
            if self.now_ns() - self._stop_ns < self.safety.unlock_delay_s * 1e9:
                return False
            self._grace = self._present_contacts()
            self._stop_ns, self.stop_reason, self.stop_tcp_speed = None, None, None
            self.arm._freeze()  # resume from where the arm is, with no stale motion
            return True

    def tool_wrench(self) -> np.ndarray:
        """The external wrench on the gripper, as the flange's force/torque sensor reports it (sim/twins/wrench.py)."""
        with self.lock:
            w = self.world
            return tool_wrench(w.model, w.data, self.geom_gripper, self.geom_robot, w.tcp_pose()[:3, 3])

    def _classify_geoms(self) -> None:
        m = self.world.model
        robot_root = m.body(ARM_BODIES[0]).id
        robot_body = np.zeros(m.nbody, bool)
        for b in range(m.nbody):
            a = b
            while a != 0 and a != robot_root:
                a = m.body_parentid[a]
            robot_body[b] = a == robot_root
        gb = m.geom_bodyid
        self.geom_weld = m.body_weldid[gb]
        self.geom_robot = robot_body[gb]
        names = [m.body(b).name for b in range(m.nbody)]
        self.geom_gripper = np.array([names[b].startswith(GRIPPER_PREFIX) for b in gb], bool)
        self.geom_pad = np.zeros(m.ngeom, bool)
        self.geom_pad[[m.geom(n).id for n in GRIPPER_PAD_GEOMS]] = True
        self.geom_movable = ~self.geom_robot & (self.geom_weld != 0)

    def _robot_contacts(self) -> tuple[dict, dict]:
        """Robot contacts as {(geom, geom): contact indices}: those that always stop (self-collision) and
        those checked against the force limit (everything else but a grasp)."""
        d = self.world.data
        n = d.ncon
        if n == 0:
            return {}, {}
        g = d.contact.geom[:n]
        g1, g2 = g[:, 0], g[:, 1]
        r1, r2 = self.geom_robot[g1], self.geom_robot[g2]
        if not np.any(r1 | r2):
            return {}, {}
        hard = (r1 & r2 & ~(self.geom_gripper[g1] & self.geom_gripper[g2])
                & (self.geom_weld[g1] != self.geom_weld[g2]))
        grasp = (self.geom_pad[g1] & self.geom_movable[g2]) | (self.geom_pad[g2] & self.geom_movable[g1])

        def keyed(mask):  # a geom pair may touch at several points (box on box): keep them all
            out: dict[tuple[int, int], list[int]] = {}
            for i in np.flatnonzero(mask):
                out.setdefault((int(min(g1[i], g2[i])), int(max(g1[i], g2[i]))), []).append(int(i))
            return out
        return keyed(hard), keyed((r1 | r2) & ~hard & ~grasp)

    def _present_contacts(self) -> set[tuple[int, int]]:
        hard, soft = self._robot_contacts()
        return set(hard) | set(soft)

    def _check_contacts(self) -> None:
        hard, soft = self._robot_contacts()
        if self._grace:
            self._grace &= set(hard) | set(soft)  # a forgiven contact that separated is no longer forgiven
        m, d = self.world.model, self.world.data
        collided = min(set(hard) - self._grace, default=None)
        if collided is not None:
            self.trigger_protective_stop(f"contact {_geom_name(m, collided[0])} <-> {_geom_name(m, collided[1])}")
            return
        f6 = np.zeros(6)
        for pair, contacts in soft.items():
            if pair in self._grace:
                continue
            normal = 0.0  # the pair's total normal force: what a force/torque sensor would feel
            for i in contacts:
                mujoco.mj_contactForce(m, d, i, f6)
                normal += abs(f6[0])
            if normal > self.safety.force_limit_n:
                speed = self._tcp_speed()
                self.trigger_protective_stop(f"contact force {normal:.0f} N > {self.safety.force_limit_n:.0f} N "
                                             f"between {_geom_name(m, pair[0])} and {_geom_name(m, pair[1])}, "
                                             f"TCP at {speed * 100:.1f} cm/s", tcp_speed=speed)
                return

    def _tcp_speed(self) -> float:
        """The TCP's linear speed now (m/s): a stop's report tells an impact from a slow press."""
        v = np.zeros(6)
        mujoco.mj_objectVelocity(self.world.model, self.world.data, mujoco.mjtObj.mjOBJ_SITE, self.world.tcp_site, v, 0)
        return float(np.linalg.norm(v[3:]))


def _geom_name(m, g: int) -> str:
    return m.geom(g).name or f"{m.body(m.geom_bodyid[g]).name}#geom{g}"
