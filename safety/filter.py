"""The safety filter: one call per control cycle turns a desired joint (or TCP) target into a safe one.

    f = SafetyFilter(default_limits("ur5e"))            # collision guard on by default
    r = f.step(desired_q, measured_q, measured_qd, now, command_time)
    robot.servo_j(r.q)                                  # r.events: what was changed, to publish/record

The filter owns the commanded stream (safety.stream: position, velocity, acceleration of what it sent) and
every limit is enforced on that stream, so what reaches the robot keeps them whatever comes in. Per cycle,
this module only orchestrates; each job has its module:

1. stop conditions (safety.conditions): e-stop / protective stop (stop_states), malformed command or
   measurement, stale, out-of-order or future command (watchdog), tracking error -> the stop policy
   (decelerate within the limits, then hold exactly still). Tracking resumes on the next valid, fresh
   command; after a stop-state recovery the stream restarts from the measured joints.
2. target (safety.shaping): joint position limits (clip), workspace (TCP box, table under the finger
   points, keep-out boxes): a target outside is projected onto the region, orientation kept, and mapped
   back with a bounded Newton IK on the desired joints' branch; if that finds no solution within its
   budget, the stop policy instead (`ik_fallback` event). The cheap FK decides whether any of it is needed.
3. tracking (safety.tracking): the target's velocity plus a catch-up of any lag, one common factor for the
   joint velocity limits (times the collision scale) and the TCP speed caps; the joint limiter
   (safety.joint_limits: jerk, acceleration, velocity with anticipation, position with braking distance;
   a target already within every limit passes bit-for-bit unchanged); the output check (safety.admissible:
   TCP caps with anticipation, the arm able to stop inside the workspace), reducing the common factor or
   handing over to the stop policy.
4. collision guard every N cycles on the predicted pose; its speed scale is held in between. At scale 0 the
   stop policy brakes, as the prediction assumed (not the common factor of step 3).

Every cycle's cost is bounded: no step runs an unbounded solver or search (IK and bisections have fixed
iteration counts), so a hostile command stream cannot make the filter overrun the control cycle.

Every intervention is reported to an EventCoalescer; `FilterResult.events` holds those opened or closed
this cycle (usually none).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from safety.conditions import StopConditions, read_command
from safety.events import EventCoalescer
from safety.fastfk import FastKinematics
from safety.inputs import vec6 as _vec6
from safety.joint_limits import JointLimiter
from safety.limits import SafetyLimits, default_limits
from safety.shaping import TargetShaper
from safety.stop_states import StopStateMachine
from safety.stream import CommandedStream
from safety.tracking import BRAKING, HOLDING, LIMITED, TRACK, Tracker
from safety.watchdog import CommandWatchdog
from safety.workspace import Workspace


class FilterResult(NamedTuple):
    q: np.ndarray  # joint target to send
    qd: np.ndarray  # its velocity (finite difference of the commanded stream)
    qdd: np.ndarray  # its acceleration
    events: tuple  # SafetyEvents opened or closed this cycle
    state: str  # stop state: "running" | "estop" | "protective_stop"
    mode: str  # "pass" (unchanged) | "limited" | "braking" (stop policy, moving) | "holding" (at rest)
    collision_scale: float
    resynced: bool  # the commanded stream restarted from the measured joints this cycle


class SafetyFilter:
    def __init__(self, limits: SafetyLimits | None = None, variant: str | None = None, collision=None,
                 stops: StopStateMachine | None = None):
        """`collision`: None -> on if limits.collision.enabled; True/False; or a ready CollisionGuard."""
        from sim.robot import TCP_OFFSET_Z, get_variant

        if limits is None:
            limits = default_limits(variant or "ur5e")
        elif variant is not None and variant != limits.variant:
            raise ValueError(f"limits are for {limits.variant!r}, not {variant!r}")
        limits.validate()
        self.limits = limits
        self.variant = get_variant(limits.variant)
        self.dt = dt = self.variant.control_period
        j = limits.joints
        self.limiter = JointLimiter(j.soft_lower, j.soft_upper, j.velocity, j.acceleration, j.jerk, dt)
        self.fk = FastKinematics(self.variant, TCP_OFFSET_Z)
        self.workspace = Workspace(limits.workspace, self.fk)
        self.watchdog = CommandWatchdog(limits.command.max_age, limits.command.max_future)
        self.events = EventCoalescer(limits.command.event_gap)
        self.stops = stops if stops is not None else StopStateMachine(limits.recovery.protective_wait)
        if self.stops.events is None:
            self.stops.events = self.events
        if collision is None:
            collision = limits.collision.enabled
        if collision is True:
            from safety.collision import CollisionGuard

            collision = CollisionGuard(limits)
        self.guard = collision or None
        if self.guard is not None:  # a guard shared with an earlier filter: its fingers open, as this one's
            self.guard.set_closure(self.workspace.closure)
        self.collision_every = max(1, round(self.variant.control_hz / limits.collision.rate_hz))
        self.collision_scale = 1.0
        self.last_collision = None
        self.stream = CommandedStream(dt, self.limiter.V, self.fk, self.workspace)
        self.conditions = StopConditions(j.max_tracking_error, self.stops, self.events, self.stream)
        self.shaper = TargetShaper(self.limiter, self.fk, self.workspace, self.events, self.stream)
        self.tracker = Tracker(limits, self.limiter, self.workspace, self.events, self.stream)
        self._cycle = 0

    # ---- state ----------------------------------------------------------------------------------------
    def reset(self, measured_q, measured_qd=None) -> None:
        """Restart the commanded stream from the measured joints (at rest unless qd is given)."""
        q = _vec6(measured_q)
        if q is None:
            raise ValueError(f"measured_q must be 6 finite joint angles, got {measured_q!r}")
        self.stream.reset(q, _vec6(measured_qd) if measured_qd is not None else None)

    @property
    def commanded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = self.stream
        return np.array(st.q), np.array(st.v), np.array(st.a)

    # ---- operator / robot -----------------------------------------------------------------------------
    def estop(self, now: float, reason: str = "software e-stop") -> None:
        self.stops.estop(now, reason)

    def reset_estop(self, now: float, operator: str) -> bool:
        return self.stops.reset_estop(now, operator)

    def report_protective_stop(self, now: float) -> None:
        self.stops.robot_protective_stop(now)

    # ---- the fingers ----------------------------------------------------------------------------------
    def set_finger_closure(self, closure: float) -> None:
        """The least closure (0 open .. 1 closed) the fingers can have until the next gripper command, which
        the controller's gripper channel knows: the finger points checked against the table and the keep-out
        boxes are placed for it (workspace.gripper_points_closed). Open until told; not a number: open."""
        if self.workspace.set_closure(closure):
            self.stream.refresh_points()
            if self.guard is not None:
                self.guard.set_closure(self.workspace.closure)

    def fingers_may_open(self, closure: float) -> bool:
        """Whether the fingers may open to `closure` where the arm is commanded now: their points there stay
        the target margin clear of the table and the keep-out boxes (or no closer than they are already, after
        a start outside). Closing is always allowed."""
        ws, st = self.workspace, self.stream
        if st.pose is None or closure >= ws.closure:
            return True
        return ws.slack_at_closure(st.pose, closure) >= min(ws.margin, st.slack)

    # ---- the cycle ------------------------------------------------------------------------------------
    def step(self, desired_q, measured_q, measured_qd, now: float, command_time: float,
             desired_tcp=None) -> FilterResult:
        st = self.stream
        mq = _vec6(measured_q)
        if st.q is None:
            if mq is None:
                raise ValueError("the first measured joint state must be 6 finite angles; cannot start from "
                                 f"{measured_q!r}")
            self.reset(mq, measured_qd)
        stop, state, resynced = self.conditions.check(mq, now)
        cmd, pose_cmd, follow = read_command(desired_q, desired_tcp, now, command_time, self.watchdog,
                                             self.events)
        target = None
        if not stop and follow:
            target = self.shaper.target(cmd, pose_cmd, now)
        if target is None or self.collision_scale <= 0.0:
            # The stop policy. Also for the guard's stop: its prediction bounded each joint's travel under the
            # stop policy; tracking at zero speed would scale all joints by one common factor and let a joint
            # headed for the contact run on while a faster one brakes. The guard's stop keeps the target as the
            # direction the command wants, so the next check can let the arm move away.
            qn, mode = self.tracker.brake()
            st.prev_target = None if target is None else target[0]
            vn, an = st.advance(qn)
        else:
            target, pose_t, pts_t, slack_t = target
            qn, mode, pose, pts, slack = self.tracker.track(target, pose_t, pts_t, slack_t,
                                                            self.collision_scale, now)
            st.prev_target = target
            vn, an = st.advance(qn, pose, pts, slack)
        self._cycle += 1
        if self.guard is not None and target is not None and self._cycle % self.collision_every == 0:
            self._collision_check(now)
        return FilterResult(np.array(qn), np.array(vn), np.array(an), self.events.flush(now), state, mode,
                            self.collision_scale, resynced)

    # ---- collision ------------------------------------------------------------------------------------
    def _collision_check(self, now):
        """Check the command and the pose it is predicted at by the next check (plus its braking travel)."""
        lim, st, dt = self.limiter, self.stream, self.dt
        q = st.q
        horizon = self.collision_every * dt
        w = st.v if any(st.v) else [0.0] * 6
        prev = st.prev_target
        if prev is not None:  # the direction the command wants to go, for an arm still at rest
            w = [w[i] if w[i] != 0.0 else (prev[i] - q[i]) / dt for i in range(6)]
        q_pred = []
        for i in range(6):
            wi = max(-lim.V[i], min(lim.V[i], w[i]))
            brake = lim.stop_bound(i, wi, st.a[i]) if wi >= 0 else -lim.stop_bound(i, -wi, -st.a[i])
            q_pred.append(q[i] + wi * horizon + brake)
        res = self.guard.check(q, q_pred)
        self.last_collision = res
        self.collision_scale = res.scale
        if res.scale <= 0.0:
            self.events.report("collision_stop", now, value=res.clearance_pred, limit=self.guard.stop,
                               message=f"stopped before a collision of {res.pair} (m of predicted clearance)")
        elif res.scale < 1.0:
            self.events.report("collision", now, value=res.clearance_pred, limit=self.guard.slow,
                               message=f"slowed near {res.pair} (m of predicted clearance)")


__all__ = ["SafetyFilter", "FilterResult", "TRACK", "LIMITED", "BRAKING", "HOLDING"]
