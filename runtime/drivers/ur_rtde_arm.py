"""URRtdeArm: a real UR5 (CB3) / UR5e (e-Series) as an `ArmDriver` over SDU Robotics' ur_rtde 1.6 (imported lazily;
`pip install ur-rtde`): RTDEControlInterface (uploads ur_rtde's control script to port 30003; commands travel in
RTDE input registers), RTDEReceiveInterface (state) and DashboardClient (29999: protective-stop unlock). Tested
with the real client against the loopback fake controller in hil_tests/fakes/ur_controller.py.

* Frequency: a raw RTDE handshake (protocol 2, GET_URCONTROL_VERSION) with a timeout asks the controller first:
  major >= 5 is an e-Series (500 Hz), else CB3 (125 Hz); an unreachable robot fails fast with ConnectionError
  instead of hanging in ur_rtde's connect, which has no timeout.
* ur_rtde holds the GIL inside every call: a synchronous moveJ would freeze every Python thread for the whole
  move and starve the watchdog, so `move_j` runs an asynchronous moveJ and polls the script's progress register.
* Watchdog (backstop for a dead host): `setWatchdog(watchdog_min_frequency)` at every script start; `state()`,
  `wait_period()` and the move loop kick it, but not within 1.5 controller cycles of a command (the script reads
  its command register once a cycle: a kick right after a servoJ would overwrite it unseen). A host quiet for
  longer gets the script stopped and the arm halted; commands return False until `unlock_protective_stop()`.
* Protective stop: commands return False, never raise or assert (Diffusion Policy's `assert servoL` killed its
  controller). `unlock_protective_stop()`: dashboard unlock (refused within the controller's 5 s: False), close
  the safety popup, clear ur_rtde's command register (registers survive the stop: the new script would execute
  the last servoJ left there), `reuploadScript`, re-arm the watchdog.
* Connection loss: ur_rtde's own reconnect fails while the robot is away, and a servoJ on a closed socket can
  report success, so every call checks both links and that samples still arrive (a pulled cable closes
  nothing), raising ConnectionError; `reconnect()` builds new interfaces.
* Time: controller `timestamp` -> host monotonic ns via the lower envelope of (host time - timestamp), leaking
  100 us/s to follow drift. Arguments are checked like the twins', within ur_rtde's own ranges.
Differences from the twin: speed_j's `time` goes to the script's speedj, which its speed thread re-issues (the
motion goes on until replaced or stopped); state fields are separate getters (a sample may straddle two packages).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time as _time
from dataclasses import dataclass
from datetime import timedelta

import numpy as np

from runtime.drivers.ur_version import frequency_for_version, query_controller_version
from sim.devices import (SERVO_GAIN_RANGE, SERVO_LOOKAHEAD_RANGE, ArmState, RobotMode, SafetyMode, check_scalar,
                         check_vector)

JOINT_LOWER = np.array([-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi])
JOINT_UPPER = -JOINT_LOWER
JOINT_SPEED_MAX = 3.14  # rad/s, ur_rtde's UR_JOINT_VELOCITY_MAX
JOINT_ACCEL_MAX = 40.0  # rad/s^2, ur_rtde's UR_JOINT_ACCELERATION_MAX
RECEIVE_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_force", "target_q",
                     "robot_mode", "safety_mode", "speed_scaling", "target_speed_fraction", "runtime_state"]
# Safety modes past sim.devices.SafetyMode (10 validate joint id, 11 undefined, 12/13 safeguard-type stops).
_EXTRA_SAFETY = {10: SafetyMode.FAULT, 11: SafetyMode.FAULT, 12: SafetyMode.SAFEGUARD_STOP,
                 13: SafetyMode.SAFEGUARD_STOP}


@dataclass(frozen=True)
class URRtdeConfig:
    host: str
    frequency: float | None = None  # Hz; None: from the controller version (500 e-Series, 125 CB3)
    watchdog_min_frequency: float = 10.0  # Hz; 0 disables the RTDE watchdog
    lookahead_time: float = 0.1  # servo_j default (s)
    gain: float = 300.0  # servo_j default
    connect_timeout_s: float = 2.0
    stale_timeout_s: float = 0.5  # no new RTDE sample for this long: ConnectionError
    move_timeout_s: float = 30.0  # margin on top of a move_j's planned duration
    settle_tol: float = 1e-3  # rad: move_j returns once every joint is this close to the goal
    restart_timeout_s: float = 5.0  # control script restart after an unlock

    def __post_init__(self):
        if not isinstance(self.host, str) or not self.host:
            raise ValueError(f"host must be a host name or address, got {self.host!r}")
        ranges = dict(frequency=(1.0, 500.0), watchdog_min_frequency=(0.0, 500.0), lookahead_time=SERVO_LOOKAHEAD_RANGE,
                      gain=SERVO_GAIN_RANGE, settle_tol=(1e-6, 0.1), connect_timeout_s=(0.01, 600.0),
                      stale_timeout_s=(0.01, 600.0), move_timeout_s=(0.01, 600.0), restart_timeout_s=(0.01, 600.0))
        for name, (lo, hi) in ranges.items():
            if getattr(self, name) is not None:
                check_scalar(name, getattr(self, name), lo, hi)


class ClockMap:
    """Controller timestamps (s) -> host monotonic ns, strictly increasing for increasing timestamps."""

    def __init__(self, leak: float = 1e-4):
        self.leak, self.offset, self._host, self._last = leak, None, 0, (None, 0)

    def __call__(self, ts: float, host_ns: int) -> int:
        sample = host_ns - ts * 1e9
        leaked = sample if self.offset is None else self.offset + self.leak * (host_ns - self._host)
        self.offset, self._host = min(leaked, sample), host_ns
        last_ts, last_ns = self._last
        if ts == last_ts:
            return last_ns
        ns = int(round(ts * 1e9 + self.offset))
        if last_ts is not None and ts > last_ts:
            ns = max(ns, last_ns + 1)
        self._last = (ts, ns)
        return ns


class URRtdeArm:
    """ArmDriver over ur_rtde. Connects in the constructor unless `connect=False`; `close()` when done."""

    def __init__(self, config: URRtdeConfig, connect: bool = True):
        self.config = config
        self._c = self._r = self._dash = None
        self._lock = threading.RLock()
        self._frequency = self._controller_hz = config.frequency or 500.0
        self.version: tuple[int, int, int, int] | None = None
        self.last_fault: str | None = None  # why the last command/unlock returned False, when known
        self._watchdog, self._last_kick, self._last_send = False, 0.0, 0.0
        if connect:
            self.connect()

    @property
    def control_period(self) -> float:
        return 1.0 / self._frequency

    @property
    def connected(self) -> bool:
        return self._c is not None and self._c.isConnected() and self._r.isConnected()

    @property
    def program_running(self) -> bool:
        """Whether ur_rtde's control script runs (False after a protective stop or a watchdog stop)."""
        return self.connected and self._c.isProgramRunning()

    # -- connection ------------------------------------------------------------------------------------------
    def connect(self) -> None:
        try:
            import dashboard_client
            import rtde_control
            import rtde_receive
        except ImportError as exc:
            raise ImportError("URRtdeArm needs ur_rtde: pip install ur-rtde") from exc
        cfg = self.config
        with self._lock:
            self._drop(stop_script=False)
            self.version = query_controller_version(cfg.host, cfg.connect_timeout_s)
            freq = cfg.frequency or frequency_for_version(self.version[0])
            try:
                self._dash = dashboard_client.DashboardClient(cfg.host)
                self._dash.connect(int(cfg.connect_timeout_s * 1000))
                self._c = rtde_control.RTDEControlInterface(cfg.host, freq)
                self._r = rtde_receive.RTDEReceiveInterface(cfg.host, freq, RECEIVE_VARIABLES)
            except RuntimeError as exc:
                self._drop(stop_script=True)
                raise ConnectionError(f"ur_rtde could not connect to the UR controller at {cfg.host}: {exc}") from exc
            self._frequency, self._controller_hz = freq, frequency_for_version(self.version[0])
            self._clock, self._fresh = ClockMap(), (None, _time.monotonic())
            self._arm_watchdog()

    def reconnect(self) -> None:
        """New interfaces after a connection loss (the control script is uploaded again)."""
        self.connect()

    def close(self) -> None:
        """Stop the control script (the controller halts the arm) and disconnect."""
        with self._lock:
            self._drop(stop_script=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _drop(self, stop_script: bool) -> None:
        c, r, dash = self._c, self._r, self._dash
        self._c = self._r = self._dash = None
        self._watchdog = False
        try:
            if stop_script and c is not None and c.isConnected():
                c.stopScript()
            if dash is not None:
                dash.disconnect()
        except RuntimeError:
            pass
        del c, r  # their destructors disconnect (ur_rtde waits 0.5 s each); disconnect() first would double it

    # -- commands --------------------------------------------------------------------------------------------
    def servo_j(self, q, velocity: float = 0.5, acceleration: float = 0.5, time: float = 0.002,
                lookahead_time: float | None = None, gain: float | None = None) -> bool:
        q = check_vector("q", q, lo=JOINT_LOWER, hi=JOINT_UPPER, unit="rad")
        v = check_scalar("velocity", velocity, 0.0, JOINT_SPEED_MAX, "rad/s")
        a = check_scalar("acceleration", acceleration, 0.0, JOINT_ACCEL_MAX, "rad/s^2")
        t = check_scalar("time", time, 0.0, 10.0, "s")
        la = check_scalar("lookahead_time", self.config.lookahead_time if lookahead_time is None else lookahead_time,
                          *SERVO_LOOKAHEAD_RANGE, "s")
        g = check_scalar("gain", self.config.gain if gain is None else gain, *SERVO_GAIN_RANGE)
        return self._command("servoJ", q.tolist(), v, a, t, la, g)

    def speed_j(self, qd, acceleration: float = 0.5, time: float = 0.0) -> bool:
        qd = check_vector("qd", qd, lo=-JOINT_SPEED_MAX, hi=JOINT_SPEED_MAX, unit="rad/s")
        a = check_scalar("acceleration", acceleration, 1e-6, JOINT_ACCEL_MAX, "rad/s^2")
        t = check_scalar("time", time, 0.0, None, "s")
        return self._command("speedJ", qd.tolist(), a, t)

    def move_j(self, q, speed: float = 1.05, acceleration: float = 1.4) -> bool:
        q = check_vector("q", q, lo=JOINT_LOWER, hi=JOINT_UPPER, unit="rad")
        v = check_scalar("speed", speed, 1e-6, JOINT_SPEED_MAX, "rad/s")
        a = check_scalar("acceleration", acceleration, 1e-6, JOINT_ACCEL_MAX, "rad/s^2")
        with self._lock:
            self._check_link()
            if self._blocked():
                return False
            op = self._c.getAsyncOperationProgressEx().operationId()
            dist = float(np.max(np.abs(q - np.asarray(self._r.getActualQ()))))
            duration = 2 * v / a + dist / v  # an upper bound of the trapezoid's duration
            if not self._command("moveJ", q.tolist(), v, a, True):
                return False
            deadline = _time.monotonic() + duration + self.config.move_timeout_s
            while True:
                self._sleep_cycle()
                if self._blocked():
                    return False
                status = self._c.getAsyncOperationProgressEx()
                if status.operationId() != op and not status.isAsyncOperationRunning():
                    break
                if _time.monotonic() > deadline:
                    self.last_fault = f"move_j did not finish within {duration + self.config.move_timeout_s:.1f} s"
                    self._c.stopJ(2.0)
                    return False
            tol = self.config.settle_tol
            return self._wait_until(lambda: np.max(np.abs(np.asarray(self._r.getActualQ()) - q)) < tol, 2.0)

    def servo_stop(self, deceleration: float = 10.0) -> None:
        self._stop("servoStop", deceleration)

    def speed_stop(self, deceleration: float = 10.0) -> None:
        self._stop("speedStop", deceleration)

    def stop(self, deceleration: float = 2.0) -> None:
        self._stop("stopJ", deceleration)

    def init_period(self) -> int:
        """ur_rtde's initPeriod (steady_clock, i.e. the host's CLOCK_MONOTONIC) in ns."""
        c = self._c
        return _time.monotonic_ns() if c is None else c.initPeriod() // timedelta(microseconds=1) * 1000

    def wait_period(self, t_start_ns: int) -> None:
        """ur_rtde's waitPeriod (one control period after `t_start_ns`); kicks the watchdog."""
        with self._lock:
            self._kick()
            c = self._c
        if c is None:
            _time.sleep(max(0.0, (int(t_start_ns) - _time.monotonic_ns()) * 1e-9 + self.control_period))
        else:
            c.waitPeriod(timedelta(microseconds=int(t_start_ns) / 1000))

    def unlock_protective_stop(self) -> bool:
        """Unlock a protective stop (False within the controller's 5 s) and restart the control script; also
        restarts a script stopped by the watchdog. False for stops a person must clear (emergency, safeguard)."""
        with self._lock:
            self._check_link()
            mode = self._safety()
            if mode == SafetyMode.PROTECTIVE_STOP:
                try:
                    self._dash.unlockProtectiveStop()
                except RuntimeError as exc:
                    self._raise_if_link_down(exc)
                    self.last_fault = f"unlock refused: {exc}"
                    return False
                if not self._wait_until(lambda: self._safety() == SafetyMode.NORMAL, 1.0):
                    return False
                with contextlib.suppress(RuntimeError):
                    self._dash.closeSafetyPopup()
            elif mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
                self.last_fault = f"safety mode {mode.name}: clear it on the pendant"
                return False
            if self._c.isProgramRunning():
                return True
            self._c.kickWatchdog()  # while stopped, ur_rtde answers any command by clearing the command register
            if not self._c.reuploadScript() or not self._wait_until(self._c.isProgramRunning,
                                                                      self.config.restart_timeout_s):
                self.last_fault = "the control script did not restart"
                return False
            self._arm_watchdog()
            return True

    # -- receive ---------------------------------------------------------------------------------------------
    def state(self) -> ArmState:
        with self._lock:
            ts = self._check_link()
            r = self._r
            q, qd = np.array(r.getActualQ(), float), np.array(r.getActualQd(), float)
            pose, target = np.array(r.getActualTCPPose(), float), np.array(r.getTargetQ(), float)
            wrench = np.array(r.getActualTCPForce(), float)
            robot_mode, safety = r.getRobotMode(), self._safety()
            scaling = min(1.0, max(0.0, r.getSpeedScaling() * r.getTargetSpeedFraction()))
            stamp = self._clock(ts, _time.monotonic_ns())
            self._kick()
        return ArmState(q=q, qd=qd, tcp_pose=pose, target_q=target, timestamp_ns=stamp,
                        robot_mode=RobotMode(robot_mode), safety_mode=safety, speed_scaling=scaling,
                        tcp_force=wrench)

    # -- internals -------------------------------------------------------------------------------------------
    def _safety(self) -> SafetyMode:
        code = self._r.getSafetyMode()
        return _EXTRA_SAFETY.get(code) or SafetyMode(code)

    def _check_link(self) -> float:
        """Raise ConnectionError unless both interfaces are connected and RTDE samples keep arriving (a dead
        link without a closed socket, e.g. a pulled cable, shows only as a timestamp that stops); the timestamp."""
        if self._c is None:
            raise ConnectionError(f"URRtdeArm({self.config.host}) is not connected; call connect() or reconnect()")
        self._raise_if_link_down(None)
        ts, now = self._r.getTimestamp(), _time.monotonic()
        if ts != self._fresh[0]:
            self._fresh = (ts, now)
        elif now - self._fresh[1] > self.config.stale_timeout_s:
            raise ConnectionError(f"no new RTDE sample from {self.config.host} for {now - self._fresh[1]:.2f} s; "
                                  "call reconnect() once the robot is reachable")
        return ts

    def _raise_if_link_down(self, cause: BaseException | None) -> None:
        if not (self._c.isConnected() and self._r.isConnected()):
            raise ConnectionError(f"lost the RTDE connection to the UR controller at {self.config.host}; call "
                                  "reconnect() once it is reachable") from cause

    def _blocked(self) -> bool:
        """True when the robot will not take commands: a safety stop, or the control script not running."""
        return self._safety() not in (SafetyMode.NORMAL, SafetyMode.REDUCED) or not self._c.isProgramRunning()

    def _command(self, name: str, *args) -> bool:
        with self._lock:
            self._check_link()
            if self._blocked():
                return False
            try:
                ok = bool(getattr(self._c, name)(*args))
                self._last_send = _time.monotonic()
            except RuntimeError as exc:
                self._raise_if_link_down(exc)
                self.last_fault = f"{name}: {exc}"
                return False
            if not ok:
                self._raise_if_link_down(None)
            return ok

    def _stop(self, name: str, deceleration: float) -> None:
        dec = check_scalar("deceleration", deceleration, 1e-6, JOINT_ACCEL_MAX, "rad/s^2")
        with self._lock:
            self._check_link()
            if not self._c.isProgramRunning():
                return  # a stopped script has already brought the arm to rest
            try:
                getattr(self._c, name)(dec)
            except RuntimeError as exc:
                self._raise_if_link_down(exc)

    def _arm_watchdog(self) -> None:
        f = self.config.watchdog_min_frequency
        self._watchdog = f > 0 and bool(self._c.setWatchdog(f))
        if f > 0 and not self._watchdog:
            self.last_fault = "setWatchdog failed"

    def _kick(self) -> None:
        """kickWatchdog, unless a command went out within 1.5 controller cycles (its package fed the watchdog)."""
        now = _time.monotonic()
        quiet = now - max(self._last_send, self._last_kick) >= 1.5 / self._controller_hz
        if self._watchdog and self._c is not None and quiet and self._c.isConnected() and self._c.isProgramRunning():
            self._c.kickWatchdog()
            self._last_kick = now

    def _sleep_cycle(self) -> None:
        t0 = self.init_period()
        self.wait_period(t0)
        self._check_link()

    def _wait_until(self, predicate, timeout_s: float) -> bool:
        deadline = _time.monotonic() + timeout_s
        while not predicate():
            if _time.monotonic() > deadline:
                return False
            self._sleep_cycle()
        return True
