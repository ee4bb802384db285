"""Output admissibility: may the arm move at these next joint velocities, and if not, how much slower?

`admissible(x)` checks what the joint limiter cannot see, for next velocities x whose joint limits (jerk,
acceleration, velocity, position with braking distance) already hold:

* TCP speed caps, linear and angular, on the pose one cycle ahead, and, anticipating the jerk limit, at
  the velocities the joints reach when their acceleration is ramped to zero from now (x + a'|a'| / 2J): the
  arm reaches a cap with zero acceleration instead of overshooting it;
* workspace braking: the arm must be able to stop with every point inside the region
  (safety.workspace.Workspace.braking_ok over the joints' travel box until rest).

`reduce` finds the largest common factor s in [0, 1] between the limiter's anchor (the zero-jerk
continuation clipped into the limits) and the candidate that is admissible, by bisection (a fixed number of
steps); the direction of motion is kept. If even the anchor is not admissible: for the TCP caps, a
synchronised brake (all joints slowed by one factor, as much as the jerk box allows), else STOP (the stop
policy, which the workspace braking check has proved keeps the arm inside).

Per cycle the constraints, the joint frames and their Jacobian terms are computed once and shared by every
check of the bisection.
"""

from __future__ import annotations

import math

from safety.fastfk import tcp_speeds
from safety.joint_limits import PASS, SCALED, STOP

REDUCE_STEPS = 10  # bisection steps of the common factor (resolution 1/1024)


class OutputCheck:
    def __init__(self, limits, limiter, workspace, events, stream):
        self.limiter, self.workspace, self.events, self.stream = limiter, workspace, events, stream
        self.dt = limiter.dt
        self.cap_lin = limits.tcp.max_linear_speed * (1 - 1e-6)
        self.cap_ang = limits.tcp.max_angular_speed * (1 - 1e-6)
        self.max_lin = limits.tcp.max_linear_speed
        self.dlo = [0.0] * 6
        self.dhi = [0.0] * 6
        self.why: str | None = None  # what the last failed check failed on: "tcp_speed" | "workspace_braking"
        ws = workspace
        self._static_cons = ws.constraints([(0.0, 0.0, 0.0)] * len(ws.offsets))
        if ws.keepout:
            self._static_cons = self._static_cons[:6 + len(ws.offsets)]
        self._cons_pts = self._cons = None
        self._cons_far = 0.0

    def constraints(self, dlo=None, dhi=None):
        """Constraints at the current output's points (keep-out faces on the side the arm is on), cached.

        With the check's joint travel box [dlo, dhi], keep-out boxes farther than any point can move in it
        (the Lipschitz bound braking_ok uses) are left out (Workspace.constraints). The list is cached with
        twice that reach, so the bisections of one cycle reuse it."""
        ws, pts = self.workspace, self.stream.pts
        if not ws.keepout:
            return self._static_cons
        travel = math.inf if dlo is None else sum(r * (h if h > -lo else -lo)
                                                  for r, lo, h in zip(ws.reach_max, dlo, dhi))
        if pts is not self._cons_pts or travel > self._cons_far:
            far = 2.0 * travel
            self._cons = self._static_cons + ws.constraints(pts, far=far)[len(self._static_cons):]
            self._cons_pts, self._cons_far = pts, far
        return self._cons

    def admissible(self, x, lin_ang=None, slack=None) -> bool:
        """TCP speed caps and workspace braking for next velocities x (position already checked).

        `lin_ang`: the TCP speeds at x when already known (then only the anticipated peak is checked);
        `slack`: the current output's min slack, enabling the Lipschitz shortcut of the braking check.
        """
        st, dt, lim = self.stream, self.dt, self.limiter
        q, v, hj, cur = st.q, st.v, lim.half_inv_j, st.pose
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
        cap_lin, cap_ang = self.cap_lin, self.cap_ang
        if lin_ang is None:
            lin_x, ang_x = tcp_speeds(cur, st.pose_of([q[i] + x[i] * dt for i in range(6)]), dt)
            if lin_x > cap_lin or ang_x > cap_ang:
                self.why = "tcp_speed"
                return False
        else:
            lin_x, ang_x = lin_ang
        # the peak needs its own FK only when the Lipschitz bounds do not already keep it under the caps
        if lin_x + rise_lin > cap_lin or ang_x + rise_ang > cap_ang:
            lin, ang = tcp_speeds(cur, st.pose_of(peak), dt)
            if lin > cap_lin or ang > cap_ang:
                self.why = "tcp_speed"
                return False
        if not self._stops_inside(x, slack):
            self.why = "workspace_braking"
            return False
        return True

    def _stops_inside(self, x, slack) -> bool:
        """Workspace braking for next velocities x (the limiter's dp/dm describe them)."""
        st = self.stream
        dlo, dhi = self.dlo, self.dhi
        self.limiter.travel_box(x, dlo, dhi)
        return self.workspace.braking_ok(st.frames, st.pts, self.constraints(dlo, dhi), dlo, dhi, slack)

    def reduce(self, res: int, out: list, now: float) -> int:
        """Largest common factor between the anchor and the candidate `out` that keeps the TCP speed caps
        and the workspace (into `out`, SCALED); STOP (the stop policy) when even the anchor does not."""
        lim, st, dt = self.limiter, self.stream, self.dt
        q, v = st.q, st.v
        if self.why == "tcp_speed":
            self.events.report("tcp_speed", now, value=None, limit=self.max_lin,
                               message="output slowed to keep the TCP speed caps")
        else:
            self.events.report("workspace_braking", now, value=st.slack, limit=0.0)
        if res == PASS:  # the anchor of a passing target: zero-jerk continuation inside the box
            a = st.a
            for i in range(6):
                c0 = v[i] + a[i] * dt
                lim.anchor[i] = lim.lo[i] if c0 < lim.lo[i] else (lim.hi[i] if c0 > lim.hi[i] else c0)
        anchor = list(lim.anchor)
        cand = list(out)
        trial = [0.0] * 6
        position_ok = lim.position_ok

        def feasible(s):
            for i in range(6):
                trial[i] = anchor[i] + s * (cand[i] - anchor[i])
                if not position_ok(i, q[i], v[i], trial[i]):
                    return False
            return self.admissible(trial)

        if not feasible(0.0):
            if self.why == "tcp_speed" and self.sync_brake(out):
                return SCALED
            return STOP
        best = list(trial)
        good, bad = 0.0, 1.0
        for _ in range(REDUCE_STEPS):
            mid = 0.5 * (good + bad)
            if feasible(mid):
                good = mid
                best[:] = trial
            else:
                bad = mid
        out[:] = best
        return SCALED

    def sync_brake(self, out: list) -> bool:
        """Slow every joint by one common factor, as much as the jerk box allows (the path is kept, the TCP
        speed drops with it), if that keeps the position and workspace limits (into `out`)."""
        lim, st = self.limiter, self.stream
        q, v = st.q, st.v
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
        return self._stops_inside(out, st.slack)


__all__ = ["OutputCheck", "REDUCE_STEPS"]
