"""Tracking: from a shaped joint target to the next commanded position, keeping every limit.

1. desired velocity: the target's own velocity plus a catch-up of any lag (the previous target minus the
   output) along a braking profile, so a lagging output closes in without overshooting;
2. one common factor for the joint velocity limits (times the collision guard's scale) and the TCP linear
   and angular speed caps (on the pose one cycle ahead): the direction of motion is kept;
3. the joint limiter (safety.joint_limits.JointLimiter.select): jerk, acceleration, velocity with
   anticipation, position with braking distance, again by one common factor;
4. the output check (safety.admissible): TCP caps with anticipation and workspace braking; if they fail,
   the largest admissible common factor, or the stop policy.

A target already within every limit passes bit-for-bit unchanged (mode TRACK); `_fast_pass` decides that in
one loop for the common case (the same checks as select + admissible). `brake` is the stop policy on its own
(no target: stop conditions, invalid or stale commands, IK fallback).
"""

from __future__ import annotations

import math

from safety.admissible import OutputCheck
from safety.fastfk import tcp_speeds
from safety.joint_limits import PASS, STOP

_PURE_LAG = 1e-12  # rad: an output this close to the previous target counts as on it (no catch-up)

# modes
TRACK, LIMITED, BRAKING, HOLDING = "pass", "limited", "braking", "holding"


class Tracker:
    def __init__(self, limits, limiter, workspace, events, stream):
        self.limiter, self.workspace, self.events, self.stream = limiter, workspace, events, stream
        self.dt = limiter.dt
        self.V = list(limiter.V)
        self.check = OutputCheck(limits, limiter, workspace, events, stream)
        self.cap_lin, self.cap_ang = self.check.cap_lin, self.check.cap_ang
        self.max_lin, self.max_ang = limits.tcp.max_linear_speed, limits.tcp.max_angular_speed
        self.out = [0.0] * 6  # the chosen next velocity (scratch, reused every cycle)
        lim, ws = limiter, workspace
        self._joint_consts = [(lim.A[i], lim.V[i], lim.c[i], lim.jdt[i], lim.half_inv_j[i], lim.L[i], lim.U[i],
                               ws.reach_max[i], ws.reach[0][i]) for i in range(6)]  # for _fast_pass

    def brake(self):
        """The stop policy's next position and mode (BRAKING, or HOLDING once at rest)."""
        st, out, dt = self.stream, self.out, self.dt
        rest = self.limiter.stop_velocity(st.v, st.a, out)
        q = st.q
        return [q[i] + out[i] * dt for i in range(6)], (HOLDING if rest else BRAKING)

    def track(self, target, pose_t, pts_t, slack_t, kc: float, now: float):
        """(next position, mode, its pose, points, slack or None x3 if not known) towards `target`;
        kc: the collision guard's speed scale."""
        ev, lim, st = self.events, self.limiter, self.stream
        q, v, a = st.q, st.v, st.a
        dt = self.dt
        prev = st.prev_target
        if prev is None:  # (re)starting: take the output as on the previous target, the target as a step
            prev = q
        pure = True
        if prev is not q:
            for i in range(6):
                d = prev[i] - q[i]
                if d > _PURE_LAG or d < -_PURE_LAG:
                    pure = False
                    break
        cur = st.pose
        if pure:
            vt = [(target[i] - q[i]) / dt for i in range(6)]
            lin, ang = tcp_speeds(cur, pose_t, dt)
            if lin <= self.cap_lin and ang <= self.cap_ang and self._fast_pass(vt, lin, ang, kc):
                return target, TRACK, pose_t, pts_t, slack_t
        else:
            vt = self._catch_up(target, prev)
        # one common factor for the joint velocity limits (times the collision scale)
        k = 1.0
        V = self.V
        for i in range(6):
            x = vt[i] if vt[i] >= 0.0 else -vt[i]
            if x * k > kc * V[i]:
                k = kc * V[i] / x
        if k < 1.0:
            ev.report("velocity", now, value=1.0 / k if k > 0 else math.inf, limit=1.0)
            vt = [x * k for x in vt]
            pure = False
        # TCP speed caps, on the pose one cycle ahead
        lin, ang = tcp_speeds(cur, pose_t if pure else st.pose_of([q[i] + vt[i] * dt for i in range(6)]), dt)
        k = 1.0
        if lin > self.cap_lin:
            k = self.cap_lin / lin
            ev.report("tcp_speed", now, value=lin, limit=self.max_lin,
                      message="TCP linear speed scaled to its cap (m/s)")
        if ang * k > self.cap_ang:
            k = self.cap_ang / ang
            ev.report("tcp_speed", now, value=ang, limit=self.max_ang, joint=None,
                      message="TCP angular speed scaled to its cap (rad/s)")
        if k < 1.0:
            vt = [x * k for x in vt]
            pure = False
        out = self.out
        res = lim.select(q, v, a, vt, out)
        if res != PASS:
            self._report_limits(vt, now)
        if res != STOP:
            # the target's TCP speed was checked; a changed velocity needs its own check
            check = self.check
            check.why = None
            if not check.admissible(out, None if not (res == PASS and pure) else (lin, ang), st.slack):
                res = check.reduce(res, out, now)
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

    def _fast_pass(self, vt, lin, ang, kc) -> bool:
        """The common case in one loop: vt inside the hard box (jerk, acceleration, velocity viability, the
        collision scale), position-feasible, the TCP caps kept with anticipation, and the workspace far
        enough for the Lipschitz test. Same checks as select + admissible; False: take the general path."""
        st = self.stream
        q, v, a = st.q, st.v, st.a
        dt = self.dt
        bound = self.limiter.stop_bound
        lip = rise_lin = rise_ang = 0.0
        i = 0
        for A, V, c, jdt, i2j, L, U, rmax, r0 in self._joint_consts:
            vi, ai, x = v[i], a[i], vt[i]
            an = (x - vi) / dt
            if an - ai > jdt or ai - an > jdt or an > A or an < -A or an > c * (V - vi) or an < c * (-V - vi):
                return False
            if x > kc * V or x < -kc * V:
                return False
            qn = q[i] + x * dt
            dp = bound(i, x, an) if x + (an * an * i2j if an > 0.0 else 0.0) > 0.0 else 0.0
            dm = bound(i, -x, -an) if -x + (an * an * i2j if an < 0.0 else 0.0) > 0.0 else 0.0
            if qn + dp > U and not (x <= 0.0 and x <= vi):
                return False
            if qn - dm < L and not (x >= 0.0 and x >= vi):
                return False
            step = x * dt
            hi = step + dp
            lo = step - dm
            if step >= 0.0:
                e = hi if hi > dm - step else dm - step
            else:
                e = -lo if -lo > hi else hi
            lip += rmax * e
            dv = an * an * i2j
            rise_lin += r0 * dv
            rise_ang += dv
            i += 1
        if lip > st.slack:
            return False
        if lin + rise_lin > self.cap_lin or ang + rise_ang > self.cap_ang:
            return False
        return True

    def _catch_up(self, target, prev):
        """Target velocity + a catch-up of the lag (prev target - output) along a braking profile."""
        q, dt, lim = self.stream.q, self.dt, self.limiter
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

    def _report_limits(self, vt, now):
        lim, st, dt = self.limiter, self.stream, self.dt
        v, a = st.v, st.a
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
            self.events.report("joint_braking", now, value=self.out[i], limit=0.0, joint=i)


__all__ = ["Tracker", "TRACK", "LIMITED", "BRAKING", "HOLDING"]
