"""SimArm: the UR arm twin, an ArmDriver with ur_rtde's command semantics on top of the MuJoCo joint servos.

The twin plays the UR controller's motion generator: each control cycle it computes the joint target
(`target_q`, as getTargetQ) and its velocity and hands them to `World.set_arm_target` (velocity as a
feed-forward lead on the position target); the MuJoCo position servos (with gravity compensation, as the
real controller) make the actual joints follow within a few milliseconds, as a UR does.

Motion models (documented because the policy learns against them):
* servo_j: the commanded q is reached through a ramp over `time` seconds (the command period; a
  command with time <= one cycle is a step), then a first-order filter with time constant
  tau = lookahead_time * 300 / gain (ur_rtde's defaults 0.1 s / 300 give tau = 0.1 s; gain 2000 with
  lookahead 0.03 gives 1.5 ms, i.e. tight tracking; gain 100 with lookahead 0.2 gives 0.6 s, i.e. smooth).
  The target's per-joint speed is capped at the joint's maximum speed.
* speed_j: the target velocity approaches `qd` at `acceleration` (rad/s^2 per joint) and the target
  integrates it; `time` > 0 ends the command after that long, decelerating at the same rate.
* move_j: a synchronised trapezoidal profile: the joint with the longest way runs at `speed` and
  `acceleration`, the others scale so all arrive together. Blocks until the arm has settled at the goal.
* servo_stop / speed_stop / stop: the current target velocity is scaled down uniformly (the path is kept)
  at `deceleration` on the fastest joint; they block until the target is at rest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.config import spec, validate
from sim.devices import (
    SERVO_GAIN_RANGE,
    SERVO_LOOKAHEAD_RANGE,
    ArmState,
    RobotMode,
    SafetyMode,
    check_scalar,
    check_vector,
)
from sim.rotations import matrix_to_rotvec

_SETTLE_TOL = 1e-3  # rad: move_j returns once every joint is this close to the goal
_MAX_ACCEL = 40.0  # rad/s^2, the most any command may ask for
_IDLE, _SERVO, _SPEED, _MOVE, _STOPPING = "idle", "servo", "speed", "move", "stopping"


@dataclass(frozen=True)
class ArmNoiseConfig:
    """Proprioception noise on what `state()` reports (the simulated joints themselves are exact)."""

    q_std: float = field(default=0.0, metadata=spec(0.0, 0.01, "rad"))
    qd_std: float = field(default=0.0, metadata=spec(0.0, 0.1, "rad/s"))
    force_std: float = field(default=0.0, metadata=spec(0.0, 20.0, "N", doc="on tcp_force (torque: x 0.1 m)"))
    seed: int = 0


class SimArm:
    """ArmDriver twin; create it through `SimRig` (it is stepped by the rig's control cycle)."""

    def __init__(self, rig, noise: ArmNoiseConfig | None = None):
        self._rig, self._world = rig, rig.world
        self.noise = noise or ArmNoiseConfig()
        validate(self.noise)
        v = self._world.variant
        self._lo, self._hi = np.array(v.joint_lower), np.array(v.joint_upper)
        self._vmax = np.array(v.max_joint_velocity)
        self._rng = np.random.default_rng(self.noise.seed)
        # Velocity feed-forward through the position servos (force = kp (target - q) - kv qd): sending
        # target + (kv / kp) v makes it kp (target - q) + kv (v - qd), so ramps track without the kv/kp lag.
        m, act = self._world.model, self._world.arm_actuators
        self._lead = -m.actuator_biasprm[act, 2] / m.actuator_gainprm[act, 0]
        self._closed = False
        self._freeze()

    @property
    def control_period(self) -> float:
        return self._rig.control_period

    # -- commands ------------------------------------------------------------------------------------------
    def servo_j(self, q, velocity: float = 0.5, acceleration: float = 0.5, time: float = 0.002,
                lookahead_time: float = 0.1, gain: float = 300.0) -> bool:
        q = check_vector("q", q, lo=self._lo, hi=self._hi, unit="rad")
        check_scalar("velocity", velocity, 0.0, None, "rad/s")
        check_scalar("acceleration", acceleration, 0.0, None, "rad/s^2")
        t = check_scalar("time", time, 0.0, 10.0, "s")
        la = check_scalar("lookahead_time", lookahead_time, *SERVO_LOOKAHEAD_RANGE, "s")
        g = check_scalar("gain", gain, *SERVO_GAIN_RANGE)
        with self._rig.lock:
            if not self._ready():
                return False
            start = self._servo_goal() if self._mode == _SERVO else self._ref.copy()
            self._mode = _SERVO
            self._servo = dict(start=start, goal=q, t=0.0, T=t, tau=la * 300.0 / g)
            return True

    def speed_j(self, qd, acceleration: float = 0.5, time: float = 0.0) -> bool:
        qd = check_vector("qd", qd, lo=-self._vmax, hi=self._vmax, unit="rad/s")
        a = check_scalar("acceleration", acceleration, 1e-6, _MAX_ACCEL, "rad/s^2")
        t = check_scalar("time", time, 0.0, None, "s")
        with self._rig.lock:
            if not self._ready():
                return False
            self._mode = _SPEED  # from the current target velocity: no jump
            until = self._rig.now_ns() + int(t * 1e9) if t > 0 else None
            self._speed = dict(goal=qd, acc=a, until=until)
            return True

    def move_j(self, q, speed: float = 1.05, acceleration: float = 1.4) -> bool:
        q = check_vector("q", q, lo=self._lo, hi=self._hi, unit="rad")
        v = check_scalar("speed", speed, 1e-6, float(self._vmax.min()), "rad/s")
        a = check_scalar("acceleration", acceleration, 1e-6, _MAX_ACCEL, "rad/s^2")
        with self._rig.lock:
            if not self._ready():
                return False
            start = self._ref.copy()
            dist = float(np.max(np.abs(q - start)))
            ta = v / a if dist >= v * v / a else math.sqrt(dist / a)  # time spent accelerating
            vpk = a * ta
            T = 2 * ta + (dist - vpk * ta) / vpk if dist > 0 else 0.0
            self._mode = _MOVE
            self._move = dict(start=start, goal=q, dist=dist, a=a, ta=ta, vpk=vpk, T=T, t=0.0)
        ok = self._rig.wait_until(lambda: self._mode != _MOVE or self._rig.protective_stopped, T + 5.0)
        settled = self._rig.wait_until(
            lambda: self._rig.protective_stopped or np.max(np.abs(self._world.arm_q() - q)) < _SETTLE_TOL, 2.0)
        return ok and settled and not self._rig.protective_stopped

    def servo_stop(self, deceleration: float = 10.0) -> None:
        self._stop_from({_SERVO}, deceleration)

    def speed_stop(self, deceleration: float = 10.0) -> None:
        self._stop_from({_SPEED}, deceleration)

    def stop(self, deceleration: float = 2.0) -> None:
        self._stop_from({_SERVO, _SPEED, _MOVE}, deceleration)

    def _stop_from(self, modes: set, deceleration: float) -> None:
        dec = check_scalar("deceleration", deceleration, 1e-6, _MAX_ACCEL, "rad/s^2")
        self._check_open()
        with self._rig.lock:
            if self._mode not in modes:
                return
            self._mode, self._decel = _STOPPING, dec
        vmax = float(np.max(np.abs(self._vel)))
        self._rig.wait_until(lambda: self._mode != _STOPPING, vmax / dec + 1.0)

    def init_period(self) -> int:
        return self._rig.now_ns()

    def wait_period(self, t_start_ns: int) -> None:
        deadline = int(t_start_ns) + self._rig._period_ns
        if self._rig.mode == "lockstep":
            while self._rig.now_ns() < deadline:
                self._rig.step(1)
        else:
            self._rig.sleep((deadline - self._rig.now_ns()) * 1e-9)

    def unlock_protective_stop(self) -> bool:
        self._check_open()
        return self._rig._unlock()

    def close(self) -> None:
        if not self._closed:
            with self._rig.lock:
                self._freeze()
            self._closed = True

    # -- receive -----------------------------------------------------------------------------------------
    def state(self) -> ArmState:
        with self._rig.lock:
            q, qd = self._world.arm_q(), self._world.arm_qd()
            T = self._world.tcp_pose()
            now = self._rig.sample_ns
            stopped = self._rig.protective_stopped
            target = self._ref.copy()
            wrench = self._rig.tool_wrench()
            if self.noise.force_std > 0:
                wrench = wrench + self._rng.normal(0.0, self.noise.force_std, 6) * np.repeat([1.0, 0.1], 3)
            if self.noise.q_std > 0:
                q = q + self._rng.normal(0.0, self.noise.q_std, 6)
            if self.noise.qd_std > 0:
                qd = qd + self._rng.normal(0.0, self.noise.qd_std, 6)
        pose = np.concatenate([T[:3, 3], matrix_to_rotvec(T[:3, :3])])
        return ArmState(q=q, qd=qd, tcp_pose=pose, target_q=target, timestamp_ns=now, robot_mode=RobotMode.RUNNING,
                        safety_mode=SafetyMode.PROTECTIVE_STOP if stopped else SafetyMode.NORMAL,
                        speed_scaling=0.0 if stopped else 1.0, tcp_force=wrench)

    # -- controller internals (called by the rig with its lock held) ---------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("this arm driver is closed; create a new one")

    def _ready(self) -> bool:
        self._check_open()
        return not self._rig.protective_stopped

    def _freeze(self) -> None:
        """Hold the current actual position with no motion (on stop, unlock and start)."""
        self._ref = np.clip(self._world.arm_q(), self._lo, self._hi)
        self._vel = np.zeros(6)
        self._mode = _IDLE
        self._world.set_arm_target(self._ref)

    def _servo_goal(self) -> np.ndarray:
        s = self._servo
        frac = 1.0 if s["T"] <= self.control_period else min(1.0, s["t"] / s["T"])
        return s["start"] + frac * (s["goal"] - s["start"])

    def _update(self, dt: float) -> None:
        if self._rig.protective_stopped:
            self._vel[:] = 0.0
            self._world.set_arm_target(self._ref)
            return
        ref, mode = self._ref, self._mode
        if mode == _SERVO:
            s = self._servo
            s["t"] += dt
            alpha = 1.0 - math.exp(-dt / s["tau"])
            step = np.clip(alpha * (self._servo_goal() - ref), -self._vmax * dt, self._vmax * dt)
            new = ref + step
        elif mode == _SPEED:
            s = self._speed
            goal = s["goal"] if s["until"] is None or self._rig.now_ns() < s["until"] else np.zeros(6)
            self._vel = self._vel + np.clip(goal - self._vel, -s["acc"] * dt, s["acc"] * dt)
            if s["until"] is not None and not np.any(self._vel) and not np.any(goal):
                self._mode = _IDLE
            new = ref + self._vel * dt
        elif mode == _MOVE:
            m = self._move
            m["t"] = min(m["t"] + dt, m["T"])
            frac = _trapezoid(m) / m["dist"] if m["dist"] > 0 else 1.0
            new = m["start"] + frac * (m["goal"] - m["start"])
            if m["t"] >= m["T"]:
                new, self._mode = m["goal"].copy(), _IDLE
        elif mode == _STOPPING:
            speed = float(np.max(np.abs(self._vel)))
            if speed <= self._decel * dt:
                self._vel[:] = 0.0
                self._mode = _IDLE
            else:
                self._vel = self._vel * (1.0 - self._decel * dt / speed)
            new = ref + self._vel * dt
        else:
            new = ref
        new = np.clip(new, self._lo, self._hi)
        if mode in (_SERVO, _MOVE):  # speed and stopping integrate their own velocity
            self._vel = (new - ref) / dt
        elif mode == _IDLE:
            self._vel = np.zeros(6)
        self._ref = new
        self._world.set_arm_target(new + self._lead * self._vel)


def _trapezoid(m: dict) -> float:
    """Distance covered at time m["t"] by the trapezoidal (or triangular) profile of duration m["T"]."""
    t, T, ta, a, vpk = m["t"], m["T"], m["ta"], m["a"], m["vpk"]
    if t <= ta:
        return 0.5 * a * t * t
    if t <= T - ta:
        return 0.5 * a * ta * ta + vpk * (t - ta)
    return m["dist"] - 0.5 * a * (T - t) ** 2
