"""The safety filter: one call per control cycle turns a desired joint (or TCP) target into a safe one.

    f = SafetyFilter(default_limits("ur5e"))            # collision guard on by default
    r = f.step(desired_q, measured_q, measured_qd, now, command_time)
    robot.servo_j(r.q)                                  # r.events: what was changed, to publish/record

The filter owns the commanded stream (position, velocity, acceleration of what it sent) and every limit is
enforced on that stream, so what reaches the robot keeps them whatever comes in. Per cycle:

1. stop conditions: e-stop / protective stop (stop_states), malformed command or measurement, stale,
   out-of-order or future command (watchdog), tracking error -> the stop policy (decelerate within the
   limits, then hold exactly still). Tracking resumes on the next valid, fresh command.
2. target: joint position limits (clip), workspace (TCP box, table under the finger points, keep-out
   boxes): a target outside is projected onto the region, orientation kept, and mapped back with IK on the
   desired joints' branch; the cheap FK decides whether that is needed at all.
3. desired velocity: the target's own velocity plus a catch-up of any lag along a braking profile, then
   scaled by one common factor for the joint velocity limits (times the collision scale) and the TCP
   linear/angular speed caps.
4. joint limits (joint_limits.JointLimiter): jerk, acceleration, velocity with anticipation, position with
   braking distance; common-factor scaling keeps the direction. A target already within every limit passes
   bit-for-bit unchanged.
5. workspace braking: the arm must be able to stop with every point inside the region
   (workspace.Workspace.braking_ok); if not, the common factor is reduced, or the stop policy takes over.
6. collision guard every N cycles on the predicted pose; its speed scale is held in between.

Every intervention is reported to an EventCoalescer; `FilterResult.events` holds those opened or closed
this cycle (usually none).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from safety.events import EventCoalescer
from safety.fastfk import FastKinematics, rotation_angle
from safety.inputs import parse_pose as _pose
from safety.inputs import vec6 as _vec6
from safety.joint_limits import PASS, SCALED, STOP, JointLimiter
from safety.limits import SafetyLimits, default_limits
from safety.stop_states import StopStateMachine
from safety.watchdog import FRESH, CommandWatchdog
from safety.workspace import Workspace

_PURE_LAG = 1e-12  # rad: an output this close to the previous target counts as on it (no catch-up)

# modes
TRACK, LIMITED, BRAKING, HOLDING = "pass", "limited", "braking", "holding"


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
        self._tcp_z = TCP_OFFSET_Z
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
        self.collision_every = max(1, round(self.variant.control_hz / limits.collision.rate_hz))
        self.collision_scale = 1.0
        self.last_collision = None
        self._kin = None
        self._V = list(self.limiter.V)
        self._cap_lin = limits.tcp.max_linear_speed * (1 - 1e-6)
        self._cap_ang = limits.tcp.max_angular_speed * (1 - 1e-6)
        self._max_track = j.max_tracking_error
        self._static_cons = self.workspace.constraints([(0.0, 0.0, 0.0)] * len(self.workspace.offsets))
        if self.workspace.keepout:
            nstat = 6 + len(self.workspace.offsets)
            self._static_cons = self._static_cons[:nstat]
        self._q: list | None = None
        self._out = [0.0] * 6
        self._dlo = [0.0] * 6
        self._dhi = [0.0] * 6
        self._cycle = 0
        self._tracking_fault = False
        self._last_cmd = self._last_shaped = None
        self._last_reports: list = []
        self._reports: list = []

    # ---- state ----------------------------------------------------------------------------------------
    def reset(self, measured_q, measured_qd=None) -> None:
        """Restart the commanded stream from the measured joints (at rest unless qd is given)."""
        q = _vec6(measured_q)
        if q is None:
            raise ValueError(f"measured_q must be 6 finite joint angles, got {measured_q!r}")
        qd = _vec6(measured_qd) if measured_qd is not None else None
        V = self._V
        self._q = q
        self._v = [0.0] * 6 if qd is None else [max(-V[i], min(V[i], qd[i])) for i in range(6)]
        self._a = [0.0] * 6
        self._prev_target = None
        self._set_pose(q)

    def _set_pose(self, q, pose=None, pts=None, slack=None):
        if pose is None:
            pose = self.fk.pose(q)
            pts = self.workspace.points((pose[0], pose[1], pose[2]), pose[3])
            slack = self.workspace.min_slack(pts)
        self._pose, self._pts, self._slack = pose, pts, slack

    @property
    def commanded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.array(self._q), np.array(self._v), np.array(self._a)

    # ---- operator / robot -----------------------------------------------------------------------------
    def estop(self, now: float, reason: str = "software e-stop") -> None:
        self.stops.estop(now, reason)

    def reset_estop(self, now: float, operator: str) -> bool:
        return self.stops.reset_estop(now, operator)

    def report_protective_stop(self, now: float) -> None:
        self.stops.robot_protective_stop(now)

    # ---- the cycle ------------------------------------------------------------------------------------
    def step(self, desired_q, measured_q, measured_qd, now: float, command_time: float,
             desired_tcp=None) -> FilterResult:
        ev = self.events
        mq = _vec6(measured_q)
        if self._q is None:
            if mq is None:
                raise ValueError("the first measured joint state must be 6 finite angles; cannot start from "
                                 f"{measured_q!r}")
            self.reset(mq, measured_qd)
        q, v, a = self._q, self._v, self._a
        dt = self.dt
        stop = False
        if mq is None:
            ev.report("malformed_measurement", now)
            stop = True
        else:
            err = 0.0
            for i in range(6):
                e = mq[i] - q[i]
                if e < 0.0:
                    e = -e
                if e > err:
                    err = e
            if err > self._max_track:
                self._tracking_fault = True
            elif self._tracking_fault and err < 0.5 * self._max_track:
                self._tracking_fault = False
            if self._tracking_fault:
                ev.report("tracking_error", now, value=err, limit=self._max_track)
                stop = True
        stops = self.stops
        if stops.protective:
            stops.update(now)
        state = stops.state
        if state != "running":
            ev.report(state, now)
            stop = True
        resynced = False
        if stops.resumed and not stop:
            if any(v) or any(a):
                stop = True  # finish the stop first, then restart from the measured joints
            else:
                stops.resumed = False
                if mq is not None:
                    self.reset(mq)
                    q, v, a = self._q, self._v, self._a
                    resynced = True

        cmd = None
        pose_cmd = None
        if desired_q is not None:
            cmd = _vec6(desired_q)
            if cmd is None:
                ev.report("malformed_command", now)
        if desired_tcp is not None:
            pose_cmd = _pose(desired_tcp)
            if pose_cmd is None:
                ev.report("malformed_command", now, message="TCP target is not a valid pose")
        valid = (cmd is not None or (desired_q is None and pose_cmd is not None)) and \
            (desired_tcp is None or pose_cmd is not None)
        if desired_q is None and desired_tcp is None:
            ev.report("malformed_command", now, message="no target given")
        status = self.watchdog.check(now, command_time)
        if status != FRESH:
            if status == "invalid":
                ev.report("malformed_command", now, message="command time or clock is not a finite number")
            else:
                ev.report(status + "_command", now, value=now - command_time if status != "out_of_order"
                          else self.watchdog.last_time - command_time,
                          limit=self.watchdog.max_age if status == "stale" else 0.0)
        out = self._out
        mode = LIMITED
        target = None
        if not stop and valid and status == FRESH:
            key = (cmd, pose_cmd)
            if key == self._last_cmd and (self._prev_target is not None or self._last_shaped is None):
                target = self._last_shaped  # the same command as last cycle: same shaped target
                for kind, value, limit, joint, message in self._last_reports:
                    ev.report(kind, now, value=value, limit=limit, joint=joint, message=message)
            else:
                self._reports = []
                target = self._shape_target(cmd, pose_cmd, now)
                self._last_cmd, self._last_shaped, self._last_reports = key, target, self._reports
        if target is None:
            rest = self.limiter.stop_velocity(v, a, out)
            mode = HOLDING if rest else BRAKING
            self._prev_target = None
            qn = [q[i] + out[i] * dt for i in range(6)]
            pose = pts = slack = None
        else:
            target, pose_t, pts_t, slack_t = target
            qn, mode, pose, pts, slack = self._track(target, pose_t, pts_t, slack_t, now)
            self._prev_target = target
        vn = [0.0] * 6
        an = [0.0] * 6
        for i in range(6):
            x = (qn[i] - q[i]) / dt
            vn[i] = x
            an[i] = (x - v[i]) / dt
        self._q, self._v, self._a = qn, vn, an
        self._set_pose(qn, pose, pts, slack)
        self._cycle += 1
        if self.guard is not None and target is not None and self._cycle % self.collision_every == 0:
            self._collision_check(now)
        return FilterResult(np.array(qn), np.array(vn), np.array(an), ev.flush(now), state, mode,
                            self.collision_scale, resynced)

    # ---- target shaping -------------------------------------------------------------------------------
    def _shape_target(self, cmd, pose_cmd, now):
        """(target joints, its pose, its points) inside joint and workspace limits, or None to hold."""
        ws = self.workspace
        if cmd is None:  # a TCP target: onto the workspace, then IK on the current branch
            p, R = pose_cmd
            if not ws.target_ok(ws.points(p, R)):
                p2 = ws.project(p, R, self._pts)
                if p2 is None:
                    self._rep("unreachable", now, message="TCP target cannot be moved into the workspace")
                    return None
                self._rep("workspace", now, value=_dist(p, p2), limit=0.0)
                p = p2
            cmd = self._ik(p, R, self._q)
            if cmd is None:
                self._rep("unreachable", now)
                return None
        target = cmd
        L, U = self.limiter.L, self.limiter.U
        for i in range(6):
            if not L[i] <= cmd[i] <= U[i]:
                target = list(cmd)  # cmd is also the cache key: clip a copy
                self._clip_joints(target, now)
                break
        pose = self.fk.pose(target)
        p = (pose[0], pose[1], pose[2])
        pts = ws.points(p, pose[3])
        slack = ws.min_slack(pts)
        if slack < ws.margin - 1e-9:
            p2 = ws.project(p, pose[3], self._pts)
            sol = self._ik(p2, pose[3], target) if p2 is not None else None
            if sol is None:
                self._rep("unreachable", now, value=slack, limit=ws.margin)
                return None
            self._rep("workspace", now, value=_dist(p, p2), limit=0.0)
            target = list(sol)
            self._clip_joints(target, now)
            pose = self.fk.pose(target)
            pts = ws.points((pose[0], pose[1], pose[2]), pose[3])
            slack = ws.min_slack(pts)
        return target, pose, pts, slack

    def _rep(self, kind, now, value=None, limit=None, joint=None, message=None):
        self.events.report(kind, now, value=value, limit=limit, joint=joint, message=message)
        self._reports.append((kind, value, limit, joint, message))

    def _clip_joints(self, target, now):
        L, U = self.limiter.L, self.limiter.U
        for i in range(6):
            x = target[i]
            if x < L[i]:
                self._rep("joint_position", now, value=x, limit=L[i], joint=i)
                target[i] = L[i]
            elif x > U[i]:
                self._rep("joint_position", now, value=x, limit=U[i], joint=i)
                target[i] = U[i]

    def _ik(self, p, R, seed):
        sol = self.fk.solve(p, R, seed)
        if sol is not None:
            return sol
        from sim.kinematics import UnreachableError

        if self._kin is None:
            from sim.kinematics import Kinematics

            self._kin = Kinematics.with_tcp_z(self.variant, self._tcp_z)
        T = np.eye(4)
        T[:3, :3] = np.reshape(R, (3, 3))
        T[:3, 3] = p
        try:
            sol = self._kin.ik(T, np.asarray(seed, dtype=float))
        except UnreachableError:
            return None
        sol = sol.tolist()
        return sol if all(math.isfinite(x) for x in sol) else None

    # ---- tracking -------------------------------------------------------------------------------------
    def _track(self, target, pose_t, pts_t, slack_t, now):
        ev, lim, ws = self.events, self.limiter, self.workspace
        q, v, a = self._q, self._v, self._a
        dt = self.dt
        prev = self._prev_target
        if prev is None:  # (re)starting: take the output as on the previous target, the target as a step
            prev = q
        pure = True
        if prev is not q:
            for i in range(6):
                d = prev[i] - q[i]
                if d > _PURE_LAG or d < -_PURE_LAG:
                    pure = False
                    break
        if pure:
            vt = [(target[i] - q[i]) / dt for i in range(6)]
            cur = self._pose
            lin = math.sqrt((pose_t[0] - cur[0]) ** 2 + (pose_t[1] - cur[1]) ** 2 + (pose_t[2] - cur[2]) ** 2) / dt
            ang = rotation_angle(cur[3], pose_t[3]) / dt
            if lin <= self._cap_lin and ang <= self._cap_ang and self._fast_pass(vt, lin, ang):
                return target, TRACK, pose_t, pts_t, slack_t
        else:
            vt = self._catch_up(target, prev)
        # one common factor for the joint velocity limits (times the collision scale)
        k = 1.0
        V, kc = self._V, self.collision_scale
        for i in range(6):
            x = vt[i] if vt[i] >= 0.0 else -vt[i]
            if x * k > kc * V[i]:
                k = kc * V[i] / x
        if k < 1.0:
            ev.report("velocity", now, value=1.0 / k if k > 0 else math.inf, limit=1.0)
            vt = [x * k for x in vt]
            pure = False
        # TCP speed caps, on the pose one cycle ahead
        if pure:
            nxt = pose_t
        else:
            nxt = self.fk.pose([q[i] + vt[i] * dt for i in range(6)])
        cur = self._pose
        lin = math.sqrt((nxt[0] - cur[0]) ** 2 + (nxt[1] - cur[1]) ** 2 + (nxt[2] - cur[2]) ** 2) / dt
        ang = rotation_angle(cur[3], nxt[3]) / dt
        self._lin, self._ang = lin, ang
        k = 1.0
        if lin > self._cap_lin:
            k = self._cap_lin / lin
            ev.report("tcp_speed", now, value=lin, limit=self.limits.tcp.max_linear_speed,
                      message="TCP linear speed scaled to its cap (m/s)")
        if ang * k > self._cap_ang:
            k = self._cap_ang / ang
            ev.report("tcp_speed", now, value=ang, limit=self.limits.tcp.max_angular_speed, joint=None,
                      message="TCP angular speed scaled to its cap (rad/s)")
        if k < 1.0:
            vt = [x * k for x in vt]
            pure = False
        out = self._out
        res = lim.select(q, v, a, vt, out)
        if res != PASS:
            self._report_limits(vt, now)
        if res != STOP:
            # the target's TCP speed was checked; a changed velocity needs its own check
            self._why = None
            if not self._admissible(out, not (res == PASS and pure), self._slack):
                res = self._reduce(res, now)
        if res == STOP:
            mode = BRAKING
            lim.stop_velocity(v, a, out)
        else:
            mode = TRACK if res == PASS and pure else LIMITED
        if mode == TRACK:
            return target, mode, pose_t, pts_t, slack_t
        qn = [q[i] + out[i] * dt for i in range(6)]
        if res == PASS and qn == target:
            return target, TRACK, pose_t, pts_t, slack_t
        return qn, mode, None, None, None

    def _fast_pass(self, vt, lin, ang) -> bool:
        """The common case in one loop: vt inside the hard box (jerk, acceleration, velocity viability, the
        collision scale), position-feasible, the TCP caps kept with anticipation, and the workspace far
        enough for the Lipschitz test. Same checks as select + _admissible; False: take the general path."""
        lim = self.limiter
        q, v, a = self._q, self._v, self._a
        dt = lim.dt
        A_, V_, c_, jdt_, hj_, L_, U_ = lim.A, lim.V, lim.c, lim.jdt, lim.half_inv_j, lim.L, lim.U
        rmax, r0 = self.workspace.reach_max, self.workspace.reach[0]
        kc = self.collision_scale
        bound = lim.stop_bound
        lip = rise_lin = rise_ang = 0.0
        for i in range(6):
            vi, ai, x, A, V, c, jdt = v[i], a[i], vt[i], A_[i], V_[i], c_[i], jdt_[i]
            an = (x - vi) / dt
            if an - ai > jdt or ai - an > jdt or an > A or an < -A or an > c * (V - vi) or an < c * (-V - vi):
                return False
            if x > kc * V or x < -kc * V:
                return False
            i2j = hj_[i]
            qn = q[i] + x * dt
            dp = bound(i, x, an) if x + (an * an * i2j if an > 0.0 else 0.0) > 0.0 else 0.0
            dm = bound(i, -x, -an) if -x + (an * an * i2j if an < 0.0 else 0.0) > 0.0 else 0.0
            if qn + dp > U_[i] and not (x <= 0.0 and x <= vi):
                return False
            if qn - dm < L_[i] and not (x >= 0.0 and x >= vi):
                return False
            step = x * dt
            hi = step + dp
            lo = step - dm
            if step >= 0.0:
                e = hi if hi > dm - step else dm - step
            else:
                e = -lo if -lo > hi else hi
            lip += rmax[i] * e
            dv = an * an * i2j
            rise_lin += r0[i] * dv
            rise_ang += dv
        if lip > self._slack:
            return False
        if lin + rise_lin > self._cap_lin or ang + rise_ang > self._cap_ang:
            return False
        self._lin, self._ang = lin, ang
        return True

    def _admissible(self, x, check_tcp: bool, slack=None, frames=None) -> bool:
        """TCP speed caps and workspace braking for next velocities x (position already checked).

        The TCP caps are checked at x and, anticipating the jerk limit, at the velocities the joints reach
        when their acceleration is ramped to zero from now (x + a'|a'| / 2J): the arm reaches the cap with
        zero acceleration instead of overshooting it. `check_tcp` False skips the check at x itself (known).
        """
        q, dt, lim = self._q, self.dt, self.limiter
        v, hj, fk, cur = self._v, lim.half_inv_j, self.fk, self._pose
        peak = [0.0] * 6
        rise_lin = rise_ang = 0.0  # Lipschitz bounds of the TCP speed change from x to the peak
        reach = self.workspace.reach[0]
        for i in range(6):
            acc = (x[i] - v[i]) / dt
            dv = (acc * acc if acc > 0.0 else -acc * acc) * hj[i]
            peak[i] = q[i] + (x[i] + dv) * dt
            dv = dv if dv > 0.0 else -dv
            rise_lin += reach[i] * dv
            rise_ang += dv
        checks = []
        if check_tcp:
            checks.append([q[i] + x[i] * dt for i in range(6)])
            lin_x = ang_x = math.inf
        else:
            lin_x, ang_x = self._lin, self._ang
        if lin_x + rise_lin > self._cap_lin or ang_x + rise_ang > self._cap_ang:
            checks.append(peak)
        for qq in checks:
            nxt = fk.pose(qq)
            lin = math.sqrt((nxt[0] - cur[0]) ** 2 + (nxt[1] - cur[1]) ** 2 + (nxt[2] - cur[2]) ** 2) / dt
            if lin > self._cap_lin or rotation_angle(cur[3], nxt[3]) / dt > self._cap_ang:
                self._why = "tcp_speed"
                return False
        lim.travel_box(x, self._dlo, self._dhi)
        if frames is None:
            frames = lambda: fk.frames(q)  # noqa: E731 (evaluated only when needed)
        if not self.workspace.braking_ok(frames, self._pts, self._constraints(), self._dlo, self._dhi, slack):
            self._why = "workspace_braking"
            return False
        return True

    def _catch_up(self, target, prev):
        """Target velocity + a catch-up of the lag (prev target - output) along a braking profile."""
        q, dt, lim = self._q, self.dt, self.limiter
        if prev is None:
            ff = [0.0] * 6
            lag = [target[i] - q[i] for i in range(6)]
        else:
            ff = [(target[i] - prev[i]) / dt for i in range(6)]
            lag = [prev[i] - q[i] for i in range(6)]
        k = 1.0
        for i in range(6):
            e = lag[i] if lag[i] >= 0.0 else -lag[i]
            if e == 0.0:
                continue
            # speed from which the joint stops within e: (1/A) u^2 + (dt + 1/c) u = e
            A, b = lim.A[i], dt + 1.0 / lim.c[i]
            u = 0.5 * A * (math.sqrt(b * b + 4.0 * e / A) - b)
            r = u * dt / e
            if r < k:
                k = r
        return [ff[i] + k * lag[i] / dt for i in range(6)]

    def _constraints(self):
        ws = self.workspace
        if not ws.keepout:
            return self._static_cons
        return self._static_cons + ws.constraints(self._pts)[len(self._static_cons):]

    def _reduce(self, res, now):
        """Largest common factor between the anchor and the candidate that keeps the TCP speed caps and the
        workspace; STOP (the stop policy) when even the anchor does not."""
        lim, q, v = self.limiter, self._q, self._v
        out, dt = self._out, self.dt
        if self._why == "tcp_speed":
            self.events.report("tcp_speed", now, value=None, limit=self.limits.tcp.max_linear_speed,
                               message="output slowed to keep the TCP speed caps")
        else:
            self.events.report("workspace_braking", now, value=self._slack, limit=0.0)
        frames = self.fk.frames(q)
        if res == PASS:  # the anchor of a passing target: zero-jerk continuation inside the box
            for i in range(6):
                c0 = v[i] + self._a[i] * dt
                lim.anchor[i] = lim.lo[i] if c0 < lim.lo[i] else (lim.hi[i] if c0 > lim.hi[i] else c0)
        anchor = list(lim.anchor)
        cand = list(out)
        trial = [0.0] * 6

        def feasible(s):
            for i in range(6):
                trial[i] = anchor[i] + s * (cand[i] - anchor[i])
                if not lim.position_ok(i, q[i], v[i], trial[i]):
                    return False
            return self._admissible(trial, True, None, frames)

        if not feasible(0.0):
            if self._why == "tcp_speed" and self._sync_brake():
                return SCALED
            return STOP
        good, bad = 0.0, 1.0
        for _ in range(10):
            mid = 0.5 * (good + bad)
            if feasible(mid):
                good = mid
            else:
                bad = mid
        feasible(good)
        out[:] = trial
        return SCALED

    def _sync_brake(self) -> bool:
        """Slow every joint by one common factor, as much as the jerk box allows (the path is kept, the TCP
        speed drops with it), if that keeps the position and workspace limits."""
        lim, q, v, out = self.limiter, self._q, self._v, self._out
        anchor = lim.anchor
        s = 1.0
        for i in range(6):
            c0 = anchor[i]
            if c0 > 0.0:
                r = (c0 - lim.lo[i]) / c0
            elif c0 < 0.0:
                r = (c0 - lim.hi[i]) / c0
            else:
                continue
            if r < s:
                s = r
        if s <= 0.0:
            return False
        for i in range(6):
            x = anchor[i] * (1.0 - s)
            x = lim.lo[i] if x < lim.lo[i] else (lim.hi[i] if x > lim.hi[i] else x)
            if not lim.position_ok(i, q[i], v[i], x):
                return False
            out[i] = x
        lim.travel_box(out, self._dlo, self._dhi)
        return self.workspace.braking_ok(lambda: self.fk.frames(q), self._pts, self._constraints(), self._dlo,
                                         self._dhi, self._slack)

    def _report_limits(self, vt, now):
        lim, v, a, dt = self.limiter, self._v, self._a, self.dt
        ra = rj = 0.0
        for i in range(6):
            acc = (vt[i] - v[i]) / dt
            jerk = (acc - a[i]) / dt
            x = abs(acc) / lim.A[i]
            if x > ra:
                ra = x
            x = abs(jerk) / lim.J[i]
            if x > rj:
                rj = x
        if ra > 1.0:
            self.events.report("acceleration", now, value=ra, limit=1.0)
        if rj > 1.0:
            self.events.report("jerk", now, value=rj, limit=1.0)
        for i in lim.braking:
            self.events.report("joint_braking", now, value=self._out[i], limit=0.0, joint=i)

    # ---- collision ------------------------------------------------------------------------------------
    def _collision_check(self, now):
        lim, q = self.limiter, self._q
        horizon = self.collision_every * self.dt
        w = self._v if any(self._v) else [0.0] * 6
        prev = self._prev_target
        if prev is not None:  # the direction the command wants to go, for an arm still at rest
            w = [w[i] if w[i] != 0.0 else (prev[i] - q[i]) / self.dt for i in range(6)]
        q_pred = []
        for i in range(6):
            wi = max(-lim.V[i], min(lim.V[i], w[i]))
            brake = lim.stop_bound(i, wi, self._a[i]) if wi >= 0 else -lim.stop_bound(i, -wi, -self._a[i])
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


def _dist(p, p2) -> float:
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(p, p2)))


__all__ = ["SafetyFilter", "FilterResult", "TRACK", "LIMITED", "BRAKING", "HOLDING"]
