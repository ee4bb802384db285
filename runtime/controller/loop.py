"""ControllerLoop: action chunks -> a C2 joint trajectory -> the safety filter -> servo_j, every control cycle.

    loop = ControllerLoop(rig.arm, rig.gripper, SafetyFilter(default_limits("ur5e")), ControllerConfig())
    loop.submit(chunk)          # any thread: IK + checks now; the loop adopts it at its next cycle
    loop.cycle(); rig.step(1)   # lockstep: one cycle per rig step (or loop.run(cycles=n): wait_period steps)
    loop.start(); ...; loop.stop()   # realtime: a thread paced by arm.init_period / wait_period

Why this shape:
* One path to the arm: every servo_j sends the SafetyFilter's output of this cycle; nothing else in this
  package commands joints (servo_stop only after the filter brought the stream to rest).
* Each cycle samples the timeline at now + execution_latency, so targets are commanded that much early.
  The watchdog's command time is min(now, last action time - latency): while the plan covers now the
  command is fresh; when chunks stop arriving it ages, and 0.1 s after the plan ran out the filter's stop
  policy holds the arm (it was already coming to rest: the spline ends at zero velocity).
* Never raises on robot trouble: protective stops go through `RecoveryDriver` (hooks for the operator),
  a robot-side e-stop latches the software e-stop (an operator resets both), other robot stop modes
  (safeguard stop, violation, fault) hold without commands, driver exceptions become events, and nothing
  planned before any stop survives it (the arm then holds at its measured joints until a new chunk).
* `submit` does the expensive part (IK, ~2 ms a knot) in the caller's thread; the loop's own cycle only
  samples splines and runs the filter (~0.1-0.4 ms), which is what keeps 500 Hz.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import NamedTuple

import numpy as np

from runtime.controller.config import ControllerConfig
from runtime.controller.contact_yield import ContactYield
from runtime.controller.gripper import GripperChannel
from runtime.controller.ik_follow import ChunkConverter, ChunkRejected
from runtime.controller.latency import LatencyEstimator
from runtime.controller.recovery import RecoveryDriver, RecoveryHooks
from runtime.controller.runner import LoopRunner
from runtime.controller.schedule import Timeline
from runtime.controller.telemetry import Telemetry
from safety.events import SafetyEvent
from sim.devices import SafetyMode

_ROBOT_HALTED = (SafetyMode.SAFEGUARD_STOP, SafetyMode.VIOLATION, SafetyMode.FAULT, SafetyMode.RECOVERY)


class _Refused(Exception):
    """The safety filter refused the measurement (its cause chained); other errors are bugs and crash."""


class CycleResult(NamedTuple):
    now: float  # s, cycle time (host monotonic / rig clock)
    desired: np.ndarray | None  # planned joint target (with any contact yield) before safety; None if it failed
    result: object  # the FilterResult (None if the cycle failed)
    sent: bool  # servo_j accepted the filter's output
    command_time: float  # the command time given to the watchdog (s)
    state: object  # the ArmState read this cycle (None if the read failed)


class ControllerLoop(LoopRunner):
    def __init__(self, arm, gripper, safety, config: ControllerConfig | None = None,
                 hooks: RecoveryHooks | None = None):
        self.cfg = cfg = config or ControllerConfig()
        cfg.validate()
        self.arm, self.gripper, self.safety = arm, gripper, safety
        self.period = float(arm.control_period)
        if abs(self.period - safety.dt) > 1e-9:
            raise ValueError(f"the arm's control period {self.period} s differs from the safety filter's "
                             f"{safety.dt} s: the limits are for another robot variant")
        lim = safety.limits
        self.timeline = Timeline(cfg, lim.joints)
        self.converter = ChunkConverter(lim.variant, cfg, lim.joints.velocity)
        self.grip = GripperChannel(gripper, lim, cfg, may_open=safety.fingers_may_open)
        self.contact = ContactYield(cfg, self.converter.kin, self.period)
        self.recovery = RecoveryDriver(safety, arm, hooks, self._emit)
        self.telemetry = Telemetry(cfg.telemetry_size, self.period, cfg.late_tolerance)
        self.latency = LatencyEstimator(self.period, cfg.latency_window)
        self.execution_latency = cfg.execution_latency
        self.last_latency_estimate: float | None = None
        self.ready = False  # True after the first complete cycle
        self.stopped = False  # True after a controlled stop finished
        self._lock = threading.RLock()
        self._events: deque = deque(maxlen=cfg.max_events)
        self._pending = None
        self._now: float | None = None
        self._prev_ns: int | None = None
        self._cmd_time: float | None = None
        self._hold_q: np.ndarray | None = None
        self._last = None  # (t_eval, p, v, a) of the latest planned sample
        self._stopping = False
        self._halted = False  # the robot is in a safety mode other than normal/reduced/protective/e-stop
        self._filter_started = False  # the filter has a commanded stream (after its first step)
        self._first_plan: float | None = None  # when the first chunk was adopted (see _idle_stale)
        self._next_estimate = -math.inf
        self._stop_req = threading.Event()
        self._thread: threading.Thread | None = None

    # ---- inputs (any thread) ---------------------------------------------------------------------------
    def submit(self, chunk) -> bool:
        """Convert and queue a chunk (the newest queued one wins). False, with an event, if rejected."""
        now = self._now
        t_eval = -math.inf if now is None else now + self.execution_latency
        fallback = self._fallback_q()
        try:
            jc = self.converter.convert(chunk, t_eval, lambda t: self.timeline.reference(t, fallback))
        except ChunkRejected as exc:
            self._emit(exc.kind, now or 0.0, str(exc), "warning" if exc.kind == "chunk_stale" else "error")
            return False
        except Exception as exc:  # a malformed message must not take the node down
            self._emit("chunk_malformed", now or 0.0, f"chunk conversion failed: {exc!r}", "error")
            return False
        with self._lock:
            self._pending = jc
        return True

    def estop(self, reason: str = "software e-stop") -> None:
        """Latch the e-stop: the filter decelerates at its maximum safe rate and holds; the plan is dropped."""
        with self._lock:
            self.safety.estop(self._now or 0.0, reason)
            self._drop_plan()

    def reset_estop(self, operator: str) -> bool:
        with self._lock:
            return self.safety.reset_estop(self._now or 0.0, operator)

    def confirm_recovery(self, operator: str) -> bool:
        """Operator confirmation of a protective-stop recovery (the last step)."""
        with self._lock:
            return self.safety.stops.confirm(self._now or 0.0, operator)

    def drain_events(self) -> list:
        """Safety and controller events since the last call (SafetyEvent objects), oldest first."""
        with self._lock:
            out = list(self._events)
            self._events.clear()
        return out

    def latency_estimate(self) -> float | None:
        """Cross-correlation estimate of the execution latency over the last window (s), or None."""
        with self._lock:  # copy under the lock, estimate outside it: the control cycle must not wait
            snapshot = self.latency.copy()
        est = snapshot.estimate()
        if est is not None:
            self.last_latency_estimate = est
        return est

    @property
    def state(self) -> str:
        s = self.safety.stops.state
        if s != "running":
            return s
        return "stopping" if self._stopping else ("tracking" if self.timeline.active else "holding")

    # ---- the cycle -------------------------------------------------------------------------------------
    def cycle(self, now_ns: int | None = None) -> CycleResult:
        """One control cycle (no waiting); `now_ns` defaults to arm.init_period()."""
        with self._lock:
            return self._cycle(now_ns)

    def _cycle(self, now_ns) -> CycleResult:
        wall = time.perf_counter()
        cfg, safety, stops = self.cfg, self.safety, self.safety.stops
        if now_ns is None:
            now_ns = self.arm.init_period()
        now = now_ns * 1e-9
        period = (now_ns - self._prev_ns) * 1e-9 if self._prev_ns is not None else math.nan
        self._prev_ns, self._now = now_ns, now
        if self._cmd_time is None:
            self._cmd_time = now
        try:
            s = self.arm.state()
        except Exception as exc:
            self._emit("driver_error", now, f"arm.state() failed: {exc!r}", "error")
            self.telemetry.record(now, period, time.perf_counter() - wall, math.nan, False, False)
            return CycleResult(now, None, None, False, self._cmd_time, None)
        arm_stopped = s.is_protective_stopped
        self.recovery.update(now, arm_stopped)
        if s.is_emergency_stopped and not stops.estopped:  # the robot's e-stop latches ours: after its
            safety.estop(now, "the robot reports an emergency stop")  # release an operator must reset both
        halted = s.safety_mode in _ROBOT_HALTED  # safeguard stop, violation, fault: hold, send nothing
        if halted != self._halted:
            mode = getattr(s.safety_mode, "name", s.safety_mode)
            self._emit("robot_halted" if halted else "robot_resumed", now, f"robot safety mode {mode}",
                       "error" if halted else "info")
            self._halted = halted
        if not stops.allows_motion or halted:
            self._drop_plan()
        if self._hold_q is None:
            self._hold_q = np.array(s.q, dtype=float)
        L = self._update_latency(now)
        t_eval = now + L
        # the periods this cycle woke too late for, on the plan they had (a pending chunk starts at t_eval)
        for k in range(self._missed_periods(period), 0, -1):
            self._filter_step(s, now - k * self.period, L, halted)
        jc, self._pending = self._pending, None
        if jc is not None and stops.allows_motion and not self._stopping:
            try:
                dropped = self.timeline.adopt(jc, t_eval, self._fallback_q())
                if self._first_plan is None:
                    self._first_plan = now
                if dropped:
                    self._emit("chunk_late", now, f"chunk arrived late: {dropped} past action(s) dropped, entered "
                                                  f"{t_eval - jc.times[0]:.3f} s after its first", "info")
            except ChunkRejected as exc:
                self._emit(exc.kind, now, str(exc), "warning")
        try:
            desired, ct, r = self._filter_step(s, now, L, halted)
            self._filter_started = True
        except _Refused as exc:  # only a malformed first measurement raises; nothing safe to send
            self._emit("driver_error", now, f"safety filter refused the measurement: {exc.__cause__!r}", "error")
            return CycleResult(now, None, None, False, self._cmd_time, s)
        sent = False
        if not arm_stopped and not halted and stops.state != "protective_stop":
            try:
                sent = bool(self.arm.servo_j(r.q, 0.5, 0.5, self.period, cfg.servo_lookahead, cfg.servo_gain))
            except Exception as exc:
                self._emit("driver_error", now, f"servo_j failed: {exc!r}", "error")
        if sent:
            self.latency.record(r.q, s.q)
        else:
            self.latency.mark_gap()
        try:
            self.grip.update(self.timeline.gripper(t_eval), now,
                             stops.allows_motion and not (self._stopping or halted), safety.events)
            safety.set_finger_closure(self.grip.closure_bound)
        except Exception as exc:
            self._emit("driver_error", now, f"gripper command failed: {exc!r}", "error")
        err = math.nan
        if self.timeline.traj is not None:
            err = float(np.max(np.abs(s.q - self.timeline.traj.eval(now)[0])))
        self.telemetry.record(now, period, time.perf_counter() - wall, err, True, sent)
        self.ready = True
        return CycleResult(now, desired, r, sent, ct, s)

    def _missed_periods(self, period: float) -> int:
        """Whole periods between the previous cycle and this one beyond the one expected, up to
        cfg.catch_up_periods. Why: each filter step moves the commanded stream one period of motion; a late
        cycle that stepped once left the arm behind its plan, and the filter's catch-up then ran it faster
        than planned (ControllerConfig's docstring). Longer gaps are stalls: the stream lags and catches up."""
        if not self._filter_started or not period > 1.5 * self.period:
            return 0
        return min(int(round(period / self.period)) - 1, self.cfg.catch_up_periods)

    def _filter_step(self, s, t: float, L: float, halted: bool):
        """One safety-filter step of the commanded stream at time t: the plan sampled at t + L (or the hold),
        the contact yield, the watchdog's command time. Returns (desired, command time, FilterResult)."""
        stops = self.safety.stops
        t_eval = t + L
        sample = self.timeline.sample(t_eval)
        if sample is None:
            desired = self._hold_q
            ct = self._cmd_time
        else:
            desired = np.array(sample[0])
            self._last = (t_eval, desired, np.array(sample[1]), np.array(sample[2]))
            ct = t if self._stopping else min(t, self.timeline.end_time - L)
        if stops.allows_motion and not halted:
            desired, change = self.contact.apply(desired, s.tcp_force)
            if change == "start":
                self._emit("contact_yield", t, f"tool force {np.linalg.norm(s.tcp_force[:3]):.0f} N > "
                                               f"{self.cfg.contact_yield_n:.0f} N: the target gives way", "info")
            elif change == "end":
                self._emit("contact_released", t, "the target is back on the plan", "info")
        ct = max(ct, self._cmd_time)  # never out of order
        self._cmd_time = ct
        try:
            r = self.safety.step(desired, s.q, s.qd, t, ct)
        except Exception as exc:
            raise _Refused() from exc
        self._events.extend(e for e in r.events if not self._idle_stale(e))
        return desired, ct, r

    def _idle_stale(self, event) -> bool:
        """A stale-command event that began before the first chunk: the watchdog's stop policy holds the arm where
        it started, as it should, but no command went stale; said at every start-up it taught operators to ignore
        the warning that matters, a policy that stops sending mid-motion."""
        return event.kind == "stale_command" and (self._first_plan is None or event.start < self._first_plan)

    def _update_latency(self, now: float) -> float:
        if self.cfg.adapt_latency and now >= self._next_estimate:
            self._next_estimate = now + 0.5 * self.cfg.latency_window
            est = self.latency.estimate()
            if est is not None:
                self.last_latency_estimate = est
        target = self.last_latency_estimate if self.cfg.adapt_latency else None
        if target is not None:  # slew-limited: the sampling time may not jump
            step = self.cfg.latency_slew * self.period
            self.execution_latency += max(-step, min(step, target - self.execution_latency))
        return self.execution_latency

    def _fallback_q(self):
        """Where the arm holds when nothing is planned: the filter's commanded joints once it has any."""
        if self._filter_started:
            return self.safety.commanded[0]
        if self._hold_q is not None:
            return self._hold_q
        return np.asarray(self.arm.state().q, dtype=float)  # before the first cycle only

    def _drop_plan(self) -> None:
        if self.timeline.active or self._pending is not None:
            self._emit("plan_dropped", self._now or 0.0, "stop: the planned chunks were discarded", "info")
        self.timeline.clear()
        self.contact.reset()
        self._pending, self._hold_q, self._last = None, None, None

    def _emit(self, kind: str, now: float, message: str, severity: str = "warning") -> None:
        self._events.append(SafetyEvent(kind=kind, severity=severity, message=message, start=now, end=now))


__all__ = ["ControllerLoop", "CycleResult", "RecoveryHooks"]
