"""Pacing and stopping the control loop: run at the control rate, in a thread, and the controlled stop.

Why separate from the cycle: these decide *when* cycles happen (arm.init_period / wait_period, as ur_rtde's
initPeriod / waitPeriod; in lockstep wait_period steps the rig) and how the loop ends, which is the part that
differs between a test stepping the rig, the realtime thread and Ctrl-C / a crash.

The controlled stop never bypasses the filter: the plan is replaced by a StopCurve (a quintic from the
current planned position, velocity and acceleration to rest, its duration sized to `budget` of the joint
acceleration and jerk limits) that is tracked through `safety.step` like any plan, with a fresh command time;
once the curve is done and both the commanded stream and the measured joints are at rest, servo_stop.
Under an e-stop or protective stop the filter is already holding; the stop then only waits for rest.
"""

from __future__ import annotations

import threading

import numpy as np

from runtime.controller.interpolate import StopCurve, stop_duration


class LoopRunner:
    """Mixin of ControllerLoop (uses its arm, cfg, safety, timeline, cycle(), _lock, _emit...)."""

    def run(self, duration_s: float | None = None, cycles: int | None = None) -> None:
        """Cycle at the control rate (arm.init_period / wait_period) until the duration or cycle count is
        reached or stop() is requested; a stop request or a crash ends with the controlled stop."""
        n, t_end, sched = 0, None, None
        p_ns = int(round(self.period * 1e9))
        self.stopped = False
        try:
            while not self._stop_req.is_set():
                t0 = self.arm.init_period()
                if t_end is None and duration_s is not None:
                    t_end = t0 + int(duration_s * 1e9)
                # wait_period sleeps until start + period; passing the scheduled start (not the actual, a
                # little late after every sleep) keeps the mean rate exact; more than a period behind: resync
                sched = t0 if sched is None or t0 - sched > p_ns else sched
                self.cycle(t0)
                n += 1
                if (cycles is not None and n >= cycles) or (t_end is not None and t0 + p_ns > t_end):
                    break
                self.arm.wait_period(sched)
                sched += p_ns
        except KeyboardInterrupt:
            self._controlled_stop()
            raise
        except Exception as exc:
            self._emit("controller_error", self._now or 0.0, f"control loop crashed: {exc!r}; stopping", "critical")
            self._stop_req.set()
        if self._stop_req.is_set():
            self._controlled_stop()
            self._stop_req.clear()

    def start(self) -> threading.Thread:
        """Run the loop in a background thread (realtime)."""
        if self._thread is None or not self._thread.is_alive():
            self._stop_req.clear()
            self._thread = threading.Thread(target=self.run, name="controller-loop", daemon=True)
            self._thread.start()
        return self._thread

    def stop(self) -> bool:
        """Controlled stop: decelerate to rest through safety, then servo_stop. True when at rest in time."""
        th = self._thread
        if th is not None and th.is_alive() and th is not threading.current_thread():
            self._stop_req.set()
            th.join(self.cfg.stop_timeout + 2.0)
            return self.stopped
        return self._controlled_stop()

    def _controlled_stop(self) -> bool:
        cfg, lim = self.cfg, self.safety.limits.joints
        at_rest = False
        try:
            with self._lock:
                self._stopping, self._pending = True, None
                if self.safety.stops.allows_motion and self._last is not None:
                    t0, p, v, a = self._last
                    T = stop_duration(v, a, lim.velocity, lim.acceleration, lim.jerk, cfg.budget)
                    self.timeline.set(StopCurve(t0, p, v, a, T))
            t_start, fallback = self._now, False
            while True:
                t0 = self.arm.init_period()
                if not fallback:
                    try:
                        res = self.cycle(t0)
                    except Exception as exc:  # the planning side is broken: let the filter brake alone
                        self._emit("controller_error", t0 * 1e-9, f"cycle failed during the stop: {exc!r}; "
                                                                  "braking with the filter's stop policy", "critical")
                        fallback = True
                if fallback:
                    res = self._brake_cycle(t0)
                if t_start is None:
                    t_start = res.now
                if res.result is not None:
                    traj = self.timeline.traj
                    done = fallback or traj is None or res.now + self.execution_latency >= traj.end
                    at_rest = done and float(np.max(np.abs(res.state.qd))) < cfg.rest_speed \
                        and float(np.max(np.abs(res.result.qd))) < cfg.rest_speed
                if at_rest or res.now - t_start > cfg.stop_timeout:
                    break
                self.arm.wait_period(t0)
            self.arm.servo_stop(cfg.servo_stop_decel)
        except Exception as exc:
            self._emit("driver_error", self._now or 0.0, f"controlled stop failed: {exc!r}", "critical")
            at_rest = False
        finally:
            with self._lock:
                self._stopping = False
                self._drop_plan()
            self.stopped = True
        self._emit("controlled_stop", self._now or 0.0, "at rest, servo stopped" if at_rest else
                   "stop timed out or failed: check the arm", "info" if at_rest else "error")
        return at_rest

    def _brake_cycle(self, now_ns):
        """A cycle without the plan: the filter gets its own commanded joints with an old command time, so
        its stop policy (watchdog: out of order / stale) decelerates within the limits and holds."""
        from runtime.controller.loop import CycleResult

        now = now_ns * 1e-9
        with self._lock:
            s = self.arm.state()
            ct = self._cmd_time - 1.0
            r = self.safety.step(self.safety.commanded[0], s.q, s.qd, now, ct)
            self._events.extend(r.events)
            sent = False
            if not s.is_protective_stopped and self.safety.stops.state != "protective_stop":
                sent = bool(self.arm.servo_j(r.q, 0.5, 0.5, self.period, self.cfg.servo_lookahead,
                                             self.cfg.servo_gain))
        return CycleResult(now, None, r, sent, ct, s)


__all__ = ["LoopRunner"]
