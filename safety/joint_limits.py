"""Joint position, velocity, acceleration and jerk limiting of the commanded stream, one 6-vector per cycle.

The commanded stream is a sequence of positions q_k sent every dt; its velocity, acceleration and jerk are
the finite differences v_k = (q_k - q_{k-1}) / dt, a_k = (v_k - v_{k-1}) / dt, j_k = (a_k - a_{k-1}) / dt,
exactly what a robot (and the tests) see. Each cycle picks the next velocity v' of every joint inside a hard
interval that keeps all limits now *and* leaves a way to keep them later (a viable set):

* jerk and acceleration: |a' - a| <= J dt, |a'| <= A;
* velocity, with anticipation (libfranka's limitRate): c (-V - v) <= a' <= c (V - v), c = J / A. With
  J dt <= A this never lets |v'| exceed V and the interval is never empty (checked by the config);
* position, with braking distance: the stop policy below, started from the next state, must end inside
  [lower, upper]. Its travel is bounded by `stop_bound`, which is monotone in v', so the feasible v' form
  an interval found by bisection (only for joints near a limit). Moving away from a limit is always allowed.

The stop policy (used by e-stop, watchdog, hold, and as the fallback when nothing else is feasible) tracks
the acceleration -c v inside the jerk/acceleration box: full deceleration while fast, then an exponential
approach to rest with time constant 1/c, snapped to exactly zero once one cycle of jerk can absorb the rest.
Because it is a fixed feedback law, following it from a state that was checked safe stays safe (the tail
of a safe stop is a safe stop), which is what makes the position and workspace invariants hold.

Limits are shrunk by `SHRINK` (relative) inside, so rounding in the finite differences never shows as a
violation at the configured values. Everything is plain Python floats on lists: on 6-vectors that is several
times faster than numpy.
"""

from __future__ import annotations

PASS, SCALED, STOP = 0, 1, 2
SHRINK = 1e-6
_BISECT = 44
FAR_MARGIN = 1e-9  # rad: a joint counts as far from its limits with at least this much to spare


class JointLimiter:
    def __init__(self, lower, upper, velocity, acceleration, jerk, dt: float, shrink: float = SHRINK):
        self.n = n = len(lower)
        self.L = [float(x) for x in lower]
        self.U = [float(x) for x in upper]
        self.V = [float(x) * (1 - shrink) for x in velocity]
        self.A = [float(x) * (1 - shrink) for x in acceleration]
        self.J = [float(x) * (1 - shrink) for x in jerk]
        self.dt = dt = float(dt)
        self.c = [self.J[i] / self.A[i] for i in range(n)]
        self.cdt = [self.c[i] * dt for i in range(n)]
        self.cdt_min = min(self.cdt)  # one approach rate for all joints keeps the direction
        self.jdt = [self.J[i] * dt for i in range(n)]
        self.snap_v = [0.5 * self.J[i] * dt * dt for i in range(n)]
        self.snap_a = [0.5 * self.J[i] * dt for i in range(n)]
        self.w = [self.A[i] / self.c[i] for i in range(n)]  # speed below which the stop is exponential
        self.half_inv_j = [0.5 / self.J[i] for i in range(n)]
        # stop_bound's constants per joint: J, A, c, w, 2J, 2A, w^2, w / c, dt
        self._sb = [(self.J[i], self.A[i], self.c[i], self.w[i], 2.0 * self.J[i], 2.0 * self.A[i],
                     self.w[i] * self.w[i], self.w[i] / self.c[i], dt) for i in range(n)]
        vmax = [self.V[i] + self.A[i] * dt for i in range(n)]  # |v'| bound from |v| <= V
        self._far_reach = [vmax[i] * dt + self.stop_bound(i, vmax[i], self.A[i]) + FAR_MARGIN for i in range(n)]
        # scratch lists reused every cycle
        self.lo = [0.0] * n
        self.hi = [0.0] * n
        self.dp = [0.0] * n  # stop travel bound, + direction, of the chosen candidate
        self.dm = [0.0] * n  # and - direction
        self.anchor = [0.0] * n
        self.braking: list[int] = []  # joints whose position interval bound the choice this cycle
        self.s = 1.0

    # ---- bounds ---------------------------------------------------------------------------------------
    def stop_bound(self, i: int, v: float, a: float) -> float:
        """Upper bound of the + direction travel of joint i under the stop policy from velocity v, accel a."""
        J, A, c, w, two_j, two_a, w2, w_c, dt = self._sb[i]
        ap = a if a > 0.0 else 0.0
        vp = v + ap * ap / two_j
        if vp <= 0.0:
            return 0.0
        k = c * vp
        if k > A:
            k = A
        t1 = (a + k) / J
        if t1 < 0.0:
            t1 = 0.0
        d = vp * (t1 + dt)
        if vp > w:
            return d + (vp * vp - w2) / two_a + w_c
        return d + vp / c

    def box(self, v, a) -> None:
        """Fill self.lo / self.hi with the hard interval of each joint's next velocity (no position)."""
        dt, lo, hi = self.dt, self.lo, self.hi
        for i in range(self.n):
            vi, ai, c, A, V, jdt = v[i], a[i], self.c[i], self.A[i], self.V[i], self.jdt[i]
            hlo = ai - jdt
            if hlo < -A:
                hlo = -A
            hhi = ai + jdt
            if hhi > A:
                hhi = A
            vlo = c * (-V - vi)
            vhi = c * (V - vi)
            amin = hlo if hlo > vlo else vlo
            amax = hhi if hhi < vhi else vhi
            if amin > amax:  # only from a state outside the viable set (e.g. initialised moving): jerk wins
                amin = amax = hhi if vlo > hhi else hlo
            lo[i] = vi + amin * dt
            hi[i] = vi + amax * dt

    def position_ok(self, i: int, q: float, v: float, vn: float) -> bool:
        """Next velocity vn keeps joint i able to stop inside its limits (or moves it away from them).

        Leaves the stop travel bounds of the resulting state in self.dp[i] / self.dm[i].
        """
        dt = self.dt
        an = (vn - v) / dt
        qn = q + vn * dt
        i2j = self.half_inv_j[i]
        # travel towards + is zero when even the worst velocity rise keeps v <= 0 (and likewise for -)
        if vn + (an * an * i2j if an > 0.0 else 0.0) <= 0.0:
            dp = 0.0
        else:
            dp = self.stop_bound(i, vn, an)
        if -vn + (an * an * i2j if an < 0.0 else 0.0) <= 0.0:
            dm = 0.0
        else:
            dm = self.stop_bound(i, -vn, -an)
        self.dp[i] = dp
        self.dm[i] = dm
        if qn + dp > self.U[i] and not (vn <= 0.0 and vn <= v):
            return False
        return qn - dm >= self.L[i] or (vn >= 0.0 and vn >= v)

    def _up_ok(self, i, q, v, x) -> bool:
        if x <= 0.0 and x <= v:
            return True
        return q + x * self.dt + self.stop_bound(i, x, (x - v) / self.dt) <= self.U[i]

    def _down_ok(self, i, q, v, x) -> bool:
        if x >= 0.0 and x >= v:
            return True
        return q + x * self.dt - self.stop_bound(i, -x, (v - x) / self.dt) >= self.L[i]

    def position_interval(self, i: int, q: float, v: float, lo: float, hi: float):
        """The position-feasible next velocities of joint i within [lo, hi], as (lo', hi'), or None."""
        if not self._up_ok(i, q, v, hi):
            if not self._up_ok(i, q, v, lo):
                return None
            hi = _last_ok(lambda x: self._up_ok(i, q, v, x), lo, hi)
        if not self._down_ok(i, q, v, lo):
            if not self._down_ok(i, q, v, hi):
                return None
            lo = _last_ok(lambda x: self._down_ok(i, q, v, x), hi, lo)
        return (lo, hi) if lo <= hi else None

    # ---- policies -------------------------------------------------------------------------------------
    def stop_velocity(self, v, a, out) -> bool:
        """The stop policy's next velocity into `out`; True when every joint is (now) at rest."""
        dt = self.dt
        rest = True
        for i in range(self.n):
            vi, ai = v[i], a[i]
            if -self.snap_v[i] <= vi <= self.snap_v[i] and -self.snap_a[i] <= ai <= self.snap_a[i]:
                out[i] = 0.0
                continue
            rest = False
            A, jdt = self.A[i], self.jdt[i]
            lo = ai - jdt
            if lo < -A:
                lo = -A
            hi = ai + jdt
            if hi > A:
                hi = A
            t = -self.c[i] * vi
            out[i] = vi + (lo if t < lo else (hi if t > hi else t)) * dt
        return rest

    def select(self, q, v, a, vt, out, approach: bool = True) -> int:
        """Next velocity as close to `vt` as the limits allow, keeping the direction of the change.

        PASS: vt itself is admissible. SCALED: out = anchor + s (vt - anchor) with the largest s in [0, 1],
        where anchor is the zero-jerk continuation clipped into the limits (so all joints are scaled by one
        common factor and the motion keeps its direction); with `approach`, each joint then also eases into
        vt at one common rate (a' <= c (vt - v), within the jerk limit), so a catch-up does not overshoot the
        target velocity. STOP: nothing is admissible (a joint cannot avoid its braking zone), out = the
        stop policy.
        """
        n, dt = self.n, self.dt
        self.box(v, a)
        lo, hi = self.lo, self.hi
        if self.braking:
            self.braking = []
        self.s = 1.0
        ok = True
        for i in range(n):
            x = vt[i]
            if x < lo[i] or x > hi[i]:
                ok = False
                break
        if ok:
            position_ok = self.position_ok
            for i in range(n):
                if not position_ok(i, q[i], v[i], vt[i]):
                    ok = False
                    break
        if ok:
            for i in range(n):
                out[i] = vt[i]
            return PASS
        blo, bhi = list(lo), list(hi)  # working bounds: hard box, narrowed by position where needed
        anchor = self.anchor
        cdt = self.cdt_min
        checked = self._far(q, v)  # joints whose whole box is position-feasible need no check
        for _ in range(n + 1):
            s = 1.0
            for i in range(n):
                c0 = v[i] + a[i] * dt
                c0 = blo[i] if c0 < blo[i] else (bhi[i] if c0 > bhi[i] else c0)
                anchor[i] = c0
                d = vt[i] - c0
                if d > 0.0:
                    r = (bhi[i] - c0) / d
                    if r < s:
                        s = r
                elif d < 0.0:
                    r = (blo[i] - c0) / d
                    if r < s:
                        s = r
            if s < 0.0:
                s = 0.0
            bad = -1
            for i in range(n):
                x = anchor[i] + s * (vt[i] - anchor[i])
                if approach:  # ease into the target velocity: a' <= c (vt - v), so it is not overshot
                    d = vt[i] - v[i]
                    if d > 0.0:
                        e = v[i] + cdt * d
                        if x > e:
                            x = e
                    elif d < 0.0:
                        e = v[i] + cdt * d
                        if x < e:
                            x = e
                x = blo[i] if x < blo[i] else (bhi[i] if x > bhi[i] else x)
                out[i] = x
                if not checked[i] and (not self.position_ok(i, q[i], v[i], anchor[i])
                                       or not self.position_ok(i, q[i], v[i], x)):
                    bad = i
                    break
            if bad < 0:
                for i in range(n):  # leave dp/dm describing the chosen velocities
                    self.position_ok(i, q[i], v[i], out[i])
                self.s = s
                return SCALED
            iv = self.position_interval(bad, q[bad], v[bad], lo[bad], hi[bad])
            if iv is None:
                break
            blo[bad] = iv[0] if iv[0] > blo[bad] else blo[bad]
            bhi[bad] = iv[1] if iv[1] < bhi[bad] else bhi[bad]
            checked[bad] = True
            self.braking.append(bad)
        self.stop_velocity(v, a, out)
        for i in range(n):
            self.position_ok(i, q[i], v[i], out[i])
        self.s = 0.0
        return STOP

    def _far(self, q, v) -> list:
        """Per joint: True when every next velocity of its hard box keeps it able to stop inside its limits.

        |v'| <= |v| + A dt = w and |a'| <= A, and the stop travel bound is monotone in both, so the joint
        moves at most w dt + stop_bound(w, A) either way (precomputed for |v| <= V; FAR_MARGIN absorbs the
        round-off of the sum).
        """
        out = [False] * self.n
        L, U, V, R = self.L, self.U, self.V, self._far_reach
        for i in range(self.n):
            vi = v[i]
            if -V[i] <= vi <= V[i]:
                reach = R[i]
            else:  # only from a state outside the viable set (e.g. initialised moving)
                w = (vi if vi >= 0.0 else -vi) + self.A[i] * self.dt
                reach = w * self.dt + self.stop_bound(i, w, self.A[i]) + FAR_MARGIN
            out[i] = L[i] < q[i] - reach and q[i] + reach < U[i]
        return out

    def travel_box(self, v_next, out_lo, out_hi) -> None:
        """Interval of each joint's displacement from now until the stop after moving at v_next for a cycle.

        Uses dp/dm left by the last position_ok/select for these velocities.
        """
        dt = self.dt
        for i in range(self.n):
            step = v_next[i] * dt
            if step >= 0.0:
                out_hi[i] = step + self.dp[i]
                x = step - self.dm[i]
                out_lo[i] = x if x < 0.0 else 0.0
            else:
                out_lo[i] = step - self.dm[i]
                x = step + self.dp[i]
                out_hi[i] = x if x > 0.0 else 0.0


__all__ = ["JointLimiter", "PASS", "SCALED", "STOP", "SHRINK"]


def _last_ok(ok, good: float, bad: float) -> float:
    """Bisect between a value where ok() holds and one where it fails: the last ok value found (_BISECT halvings)."""
    for _ in range(_BISECT):
        mid = 0.5 * (good + bad)
        if ok(mid):
            good = mid
        else:
            bad = mid
    return good
