"""Cartesian limits: the TCP box, the table plane under the finger points, and keep-out boxes.

Two jobs:

* Targets. `target_ok` tests a target pose against the region shrunk by `target_margin`; `project` moves a
  TCP target onto that region keeping its orientation: clip into the box, lift until every finger point
  clears the table, push out of keep-out boxes through the face on the side where the arm already is (so a
  target sweeping through a box slides along its face instead of jumping to the far side). The caller maps
  the result back to joints with IK seeded on the desired joints (same branch).

Against a keep-out box the gripper is the convex hull of its points (the TCP and the finger points), not the
points alone: it is clear of a box only when all its points lie beyond one common face of it. Points outside
on different sides (a bin wall 8 mm thick between two fingertips 104 mm apart) are a hit, as the pads and the
fingers' links between them would be. A common face is conservative next to a box's edge (a hull yawed past a
corner can be clear with no face between), never optimistic.

* The output. `braking_ok` proves that the commanded arm can still stop without any point leaving the
  region: the joints' travel until rest lies in a box [lo_i, hi_i] (from the stop policy's bound), and for
  each constraint n.P <= b it bounds n.P over that whole joint box by a Taylor expansion with an exact
  remainder bound: n.P(q) + sum_i max(g_i lo_i, g_i hi_i) + 1/2 sum_ij |d_i||d_j| R_max(i,j), where
  g_i = n.(axis_i x (P - o_i)) and R_j bounds the point's distance from joint axis j (so |d2P/dq_i dq_j|
  <= R_max(i,j)). Far from every boundary a cheaper Lipschitz test (sum_i R_i |d_i| <= slack) suffices.
  A constraint already violated (the arm started outside the region) only admits motion whose first-order
  effect leads back inside; the rigorous bound applies again once it is inside.
"""

from __future__ import annotations

import math

_INWARD = 1e-9  # m: projections aim this far inside, so round-off does not leave them on the wrong side


class Workspace:
    def __init__(self, limits, fk):
        self.fk = fk
        self.bmin = tuple(float(x) for x in limits.box_min)
        self.bmax = tuple(float(x) for x in limits.box_max)
        self.zt = float(limits.table_z + limits.finger_clearance)
        self.margin = float(limits.target_margin)
        self.keepout = tuple(tuple(float(x) for x in b) for b in limits.keepout)
        self._open = tuple(tuple(float(x) for x in p) for p in limits.gripper_points)
        self._closed = tuple(tuple(float(x) for x in p) for p in limits.gripper_points_closed) or self._open
        self.closure = 0.0
        self._grip = self._open
        self.offsets = ((0.0, 0.0, 0.0),) + self._grip
        reach = fk.axis_reach
        # from the farther of each point's open and closed place: a bound for every closure in between
        far = [(0.0, 0.0, 0.0)] + [max(a, b, key=lambda p: sum(x * x for x in p)) for a, b in zip(self._open,
                                                                                             self._closed)]
        self.reach = tuple(tuple(r + math.sqrt(sum(x * x for x in off)) for r in reach) for off in far)
        self.reach_max = tuple(max(r[i] for r in self.reach) for i in range(len(reach)))
        self._g_key: tuple = (None, None)  # (frames, points) the cached gradients belong to
        self._g: dict = {}

    def set_closure(self, closure: float) -> bool:
        """Place the finger points for the least closure the fingers can have (0 open .. 1 closed, clipped;
        anything not a number counts as open). Returns whether the points moved."""
        c = clip_closure(closure)
        if c == self.closure:
            return False
        self.closure, self._grip = c, self._grip_at(c)
        self.offsets = ((0.0, 0.0, 0.0),) + self._grip
        return True

    def slack_at_closure(self, pose, closure: float) -> float:
        """min_slack of an fk.pose with the finger points placed for `closure` (the current ones kept)."""
        return self.min_slack(self.points((pose[0], pose[1], pose[2]), pose[3], self._grip_at(clip_closure(closure))))

    def _grip_at(self, c: float) -> tuple:
        return tuple(tuple(o + c * (k - o) for o, k in zip(po, pk)) for po, pk in zip(self._open, self._closed))

    # ---- points and slacks ----------------------------------------------------------------------------
    def points(self, p, R, grip=None):
        """World positions of the TCP (first) and the gripper points (`grip`: other points in the TCP frame)."""
        px, py, pz = p
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = R
        out = [p]
        for x, y, z in self._grip if grip is None else grip:
            out.append((px + r0 * x + r1 * y + r2 * z, py + r3 * x + r4 * y + r5 * z, pz + r6 * x + r7 * y + r8 * z))
        return out

    def at(self, pose):
        """(points, min slack) of an fk.pose (px, py, pz, R)."""
        pts = self.points((pose[0], pose[1], pose[2]), pose[3])
        return pts, self.min_slack(pts)

    def constraints(self, pts, ref_pts=None, far: float | None = None):
        """[(point index, axis, sign, bound)]: sign * P[axis] <= bound, for these points.

        Keep-out boxes contribute, for every point, the one face the gripper's hull is most clearly outside
        of (in `ref_pts`, the current output's points, when given), so the check follows the side the arm is
        on and keeps the whole hull there. `far` (without ref_pts): leave out boxes the hull lies more than
        this beyond; their common face's slack exceeds it for every point, so a braking check whose Lipschitz
        travel is at most `far` skips them anyway.
        """
        out = []
        for axis in range(3):
            out.append((0, axis, -1.0, -self.bmin[axis]))
            out.append((0, axis, 1.0, self.bmax[axis]))
        for k in range(len(pts)):
            out.append((k, 2, -1.0, -self.zt))
        cull = far is not None and ref_pts is None and self.keepout
        a = _aabb(pts) if cull else None
        for box in self.keepout:
            if cull and _box_gap(box, a) > far:
                continue
            axis, sign, bound = _common_face(box, ref_pts if ref_pts is not None else pts)
            out.extend((k, axis, sign, bound) for k in range(len(pts)))
        return out

    def min_slack(self, pts, margin: float = 0.0) -> float:
        """Smallest distance inside the region over all constraints (negative: violated by that much)."""
        x, y, z = pts[0]
        b0, b1, b2 = self.bmin
        B0, B1, B2 = self.bmax
        s = x - b0
        for d in (B0 - x, y - b1, B1 - y, z - b2, B2 - z):
            if d < s:
                s = d
        zt = self.zt
        for P in pts:
            d = P[2] - zt
            if d < s:
                s = d
        if self.keepout:
            # the hull's gap to a box is its bounding box's: one pass over the points serves every box
            # (_box_gap written out: this runs every cycle, for every box)
            xlo, ylo, zlo, xhi, yhi, zhi = _aabb(pts)
            for b in self.keepout:
                d = max(b[0] - xhi, xlo - b[3], b[1] - yhi, ylo - b[4], b[2] - zhi, zlo - b[5])
                if d < s:
                    s = d
        return s - margin

    def target_ok(self, pts, tol: float = 0.0) -> bool:
        return self.min_slack(pts, self.margin) >= -tol

    # ---- target projection ----------------------------------------------------------------------------
    def project(self, p, R, ref_pts):
        """TCP position moved onto the target region (orientation R kept), or None if none is found."""
        m = self.margin + _INWARD
        lo = [self.bmin[i] + m for i in range(3)]
        hi = [self.bmax[i] - m for i in range(3)]
        offs = [(R[6] * o[0] + R[7] * o[1] + R[8] * o[2]) for o in self.offsets]  # z of each point above TCP
        rot = [(R[0] * o[0] + R[1] * o[1] + R[2] * o[2], R[3] * o[0] + R[4] * o[1] + R[5] * o[2], dz)
               for o, dz in zip(self.offsets, offs)]
        x = [p[0], p[1], p[2]]
        for _ in range(4):
            for i in range(3):
                x[i] = lo[i] if x[i] < lo[i] else (hi[i] if x[i] > hi[i] else x[i])
            zmin = self.zt + m - min(offs)
            if x[2] < zmin:
                x[2] = zmin
            moved = False
            for box in self.keepout:
                b = (box[0] - m, box[1] - m, box[2] - m, box[3] + m, box[4] + m, box[5] + m)
                pts = [(x[0] + r[0], x[1] + r[1], x[2] + r[2]) for r in rot]
                if _hull_separation(b, pts) >= 0.0:
                    continue
                axis, sign, bound = _common_face(b, ref_pts if ref_pts is not None else pts)
                worst = max(sign * P[axis] - bound for P in pts)  # > 0: the hull is past that face
                if worst > 0.0:
                    x[axis] -= sign * (worst + 1e-9)
                    moved = True
            if not moved and self.target_ok(self.points(tuple(x), R), _INWARD):
                return tuple(x)
        return tuple(x) if self.target_ok(self.points(tuple(x), R), _INWARD) else None

    # ---- braking check on the output ------------------------------------------------------------------
    def braking_ok(self, frames, pts, cons, dlo, dhi, slack: float | None = None) -> bool:
        """Every point stays inside while the joints travel anywhere in [q + dlo, q + dhi].

        `frames` = FastKinematics.frames(q) (or a zero-arg callable giving it, evaluated only if needed),
        `pts` the points at q, `cons` their constraints, `slack` their min_slack if known (fast path).
        The first-order terms g depend only on q, so they are kept for the next call with the same `frames`
        and `pts` objects (the bisections of one cycle; neither may be changed in place between calls). Six
        joints, loops written out; the sums are taken in joint order, as a loop would.
        """
        lo0, lo1, lo2, lo3, lo4, lo5 = dlo
        hi0, hi1, hi2, hi3, hi4, hi5 = dhi
        e0 = hi0 if hi0 > -lo0 else -lo0
        e1 = hi1 if hi1 > -lo1 else -lo1
        e2 = hi2 if hi2 > -lo2 else -lo2
        e3 = hi3 if hi3 > -lo3 else -lo3
        e4 = hi4 if hi4 > -lo4 else -lo4
        e5 = hi5 if hi5 > -lo5 else -lo5
        r0, r1, r2, r3, r4, r5 = self.reach_max
        if slack is not None and r0 * e0 + r1 * e1 + r2 * e2 + r3 * e3 + r4 * e4 + r5 * e5 <= slack:
            return True  # Lipschitz: no point can move farther than this
        fr = None
        lips = {}  # per point: its Lipschitz bound and second-order remainder for this travel box
        for k, axis, sign, bound in cons:
            slack_k = bound - sign * pts[k][axis]
            if slack_k < 0.0:  # already outside (start-up): allow only motion that leads back in
                if fr is None:
                    fr = self._frames_for(frames, pts)
                if self._outward(fr, pts[k], axis, sign, dlo, dhi) > 0.0:
                    return False
                continue
            lk = lips.get(k)
            if lk is None:
                r0, r1, r2, r3, r4, r5 = self.reach[k]
                lk = lips[k] = [r0 * e0 + r1 * e1 + r2 * e2 + r3 * e3 + r4 * e4 + r5 * e5, None]
            if lk[0] <= slack_k:
                continue
            if fr is None:
                fr = self._frames_for(frames, pts)
            second = lk[1]
            if second is None:  # sum_ij |d_i||d_j| R[max(i, j)], R[j]: the bound of the later joint
                r0, r1, r2, r3, r4, r5 = self.reach[k]
                p2 = e0 + e1
                p3 = p2 + e2
                p4 = p3 + e3
                p5 = p4 + e4
                second = lk[1] = (r0 * e0 * e0 + r1 * e1 * (e1 + 2.0 * e0) + r2 * e2 * (e2 + 2.0 * p2)
                                  + r3 * e3 * (e3 + 2.0 * p3) + r4 * e4 * (e4 + 2.0 * p4) + r5 * e5 * (e5 + 2.0 * p5))
            g = self._g.get((k, axis, sign))
            if g is None:
                g = self._g[(k, axis, sign)] = self._gradient(fr, pts[k], axis, sign)
            g0, g1, g2, g3, g4, g5 = g
            t0, u0 = g0 * hi0, g0 * lo0
            t1, u1 = g1 * hi1, g1 * lo1
            t2, u2 = g2 * hi2, g2 * lo2
            t3, u3 = g3 * hi3, g3 * lo3
            t4, u4 = g4 * hi4, g4 * lo4
            t5, u5 = g5 * hi5, g5 * lo5
            first = ((t0 if t0 > u0 else u0) + (t1 if t1 > u1 else u1) + (t2 if t2 > u2 else u2)
                     + (t3 if t3 > u3 else u3) + (t4 if t4 > u4 else u4) + (t5 if t5 > u5 else u5))
            if first + 0.5 * second > slack_k:
                return False
        return True

    def _frames_for(self, frames, pts):
        """The frames (evaluating a callable), resetting the gradient cache when they or the points change."""
        fr = frames() if callable(frames) else frames
        if fr is not self._g_key[0] or pts is not self._g_key[1]:
            self._g_key = (fr, pts)
            self._g = {}
        return fr

    @staticmethod
    def _gradient(fr, P, axis, sign):
        """g_i = sign * component `axis` of axis_i x (P - origin_i): d(sign * P[axis]) / dq_i."""
        _, _, axes, origins = fr
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        return [sign * (ax[a1] * (P[a2] - o[a2]) - ax[a2] * (P[a1] - o[a1])) for ax, o in zip(axes, origins)]

    @staticmethod
    def _outward(fr, P, axis, sign, dlo, dhi) -> float:
        """First-order change of sign * P[axis] for the middle of the joint travel box."""
        _, _, axes, origins = fr
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        out = 0.0
        for i in range(len(dlo)):
            ax, o = axes[i], origins[i]
            g = sign * (ax[a1] * (P[a2] - o[a2]) - ax[a2] * (P[a1] - o[a1]))
            out += g * 0.5 * (dlo[i] + dhi[i])
        return out


def clip_closure(x) -> float:
    """A closure in [0, 1]; anything not a finite number is open (0), the widest the fingers can be."""
    try:
        c = float(x)
    except (TypeError, ValueError):
        return 0.0
    return min(1.0, max(0.0, c)) if math.isfinite(c) else 0.0


def _aabb(pts) -> tuple:
    """(xmin, ymin, zmin, xmax, ymax, zmax) of the points."""
    xs, ys, zs = zip(*pts)
    return min(xs), min(ys), min(zs), max(xs), max(ys), max(zs)


def _box_gap(box, a) -> float:
    """How far the axis-aligned box `a` lies beyond one face of `box` (> 0 clear, <= 0 overlapping)."""
    return max(box[0] - a[3], a[0] - box[3], box[1] - a[4], a[1] - box[4], box[2] - a[5], a[2] - box[5])


def _hull_separation(box, pts) -> float:
    """How far the convex hull of pts lies beyond one common face of the box (max over faces of the nearest
    point's distance past it): > 0 clear of the box; <= 0 when no face has every point beyond it. The nearest
    point past a face is an extreme of the points along its axis, so this is the points' bounding box's gap."""
    return _box_gap(box, _aabb(pts))


def _common_face(box, pts):
    """(axis, sign, bound) of the box face that all of pts are most outside of (the largest distance of the
    nearest point past it): sign * P[axis] <= bound for every point keeps their hull out of the box."""
    best, face = -math.inf, None
    for axis in range(3):
        c = [P[axis] for P in pts]
        d = box[axis] - max(c)  # beyond the min face: P[axis] <= box_min
        if d > best:
            best, face = d, (axis, 1.0, box[axis])
        d = min(c) - box[axis + 3]  # beyond the max face: -P[axis] <= -box_max
        if d > best:
            best, face = d, (axis, -1.0, -box[axis + 3])
    return face


__all__ = ["Workspace", "clip_closure"]
