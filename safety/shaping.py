"""Target shaping: a valid command becomes a joint target inside the joint and workspace limits, or None.

* A joint target is clipped into the (soft) joint position limits.
* A TCP target is moved onto the workspace's target region (safety.workspace.Workspace.project: orientation
  kept) and mapped to joints by IK seeded on the current output (the arm's branch).
* A joint target whose TCP or finger points lie outside the region (the cheap FK decides whether that is
  needed at all) is projected the same way and mapped back by IK seeded on the desired joints (their branch).

IK is the Newton solve of safety.fastfk, bounded, never a full solver: at most IK_ITERS iterations a solve
and IK_BUDGET a cycle, so a hostile stream cannot make a cycle expensive. It is seeded on the branch seed
(the desired joints for a projection, the current output for a TCP target); a solution is accepted when it
lies within IK_MAX_DEV of that seed (the seed's branch), or of last cycle's solution of the same kind (warm
start: a target sliding along a face of the region stays on the branch it was accepted on). If Newton from
the branch seed does not converge (a first step too large, a singular Jacobian, out of iterations), last
cycle's solution is tried as the seed with what is left of the budget; a solution it did converge to that
is near neither is another branch, and is not followed.
When neither gives a solution (the target is far from both, near a singularity, or only reachable on
another branch), the shaper returns None with an `ik_fallback` event, and the filter follows its stop policy
this cycle: decelerate along the current motion within the acceleration and jerk limits, then hold still.
That is the policy of every stop condition, so it keeps every limit; a later command that Newton can reach
is followed again.

The same command as last cycle (the policy repeating its target) gives the same shaped target without any
computation, and its interventions are reported again so their events stay open.
"""

from __future__ import annotations

import math

IK_ITERS = 8  # Newton iterations per solve (converged solves take 2-6)
IK_BUDGET = 12  # Newton iterations per cycle, all solves together (~15 us each)
IK_MAX_DEV = 0.3  # rad (every joint): how far a solution may lie from its branch seed or last solution


class TargetShaper:
    def __init__(self, limiter, fk, workspace, events, stream, ik_iters: int = IK_ITERS,
                 ik_budget: int = IK_BUDGET):
        self.limiter, self.fk, self.workspace, self.events, self.stream = limiter, fk, workspace, events, stream
        self.ik_iters, self.ik_budget = int(ik_iters), int(ik_budget)
        self._budget = 0
        self._warm = {}  # last shaping's IK solutions by kind ("tcp", "projection")
        self._last_cmd = self._last_shaped = None
        self._last_reports: list = []
        self._reports: list = []

    def target(self, cmd, pose_cmd, now: float):
        """(target joints, its pose, points, slack) for a valid fresh command, or None (stop policy)."""
        key = (cmd, pose_cmd)
        if key == self._last_cmd and (self.stream.prev_target is not None or self._last_shaped is None):
            report = self.events.report
            for kind, value, limit, joint, message in self._last_reports:
                report(kind, now, value=value, limit=limit, joint=joint, message=message)
            return self._last_shaped  # the same command as last cycle: same shaped target
        self._reports = []
        self._budget = self.ik_budget
        warm, self._warm = self._warm, {}  # solutions of the previous shaping only: warm starts stay continuous
        shaped = self._shape(cmd, pose_cmd, warm, now)
        self._last_cmd, self._last_shaped, self._last_reports = key, shaped, self._reports
        return shaped

    def _shape(self, cmd, pose_cmd, warm, now):
        ws, stream = self.workspace, self.stream
        if cmd is None:  # a TCP target: onto the workspace, then IK on the current branch
            p, R = pose_cmd
            if not ws.target_ok(ws.points(p, R)):
                p2 = ws.project(p, R, stream.pts)
                if p2 is None:
                    self._rep("unreachable", now, message="TCP target cannot be moved into the workspace")
                    return None
                self._rep("workspace", now, value=_dist(p, p2), limit=0.0)
                p = p2
            cmd = self._ik(p, R, stream.q, warm, "tcp", now)
            if cmd is None:
                return None
        target = cmd
        L, U = self.limiter.L, self.limiter.U
        for i in range(6):
            if not L[i] <= cmd[i] <= U[i]:
                target = list(cmd)  # cmd is also the cache key: clip a copy
                self._clip_joints(target, now)
                break
        pose = self.fk.pose(target)
        pts, slack = ws.at(pose)
        if slack < ws.margin - 1e-9:
            p = (pose[0], pose[1], pose[2])
            p2 = ws.project(p, pose[3], stream.pts)
            if p2 is None:
                self._rep("unreachable", now, value=slack, limit=ws.margin)
                return None
            sol = self._ik(p2, pose[3], target, warm, "projection", now)
            if sol is None:
                return None
            self._rep("workspace", now, value=_dist(p, p2), limit=0.0)
            target = list(sol)
            self._clip_joints(target, now)
            pose = self.fk.pose(target)
            pts, slack = ws.at(pose)
        return target, pose, pts, slack

    def _ik(self, p, R, seed, warm, kind, now):
        """Joints reaching (p, R) on the branch of `seed` (or of warm[kind]), or None with an ik_fallback event."""
        fk = self.fk
        last = warm.get(kind)
        for start in (seed, last):
            iters = min(self.ik_iters, self._budget)
            if start is None or iters <= 0:
                continue
            sol = fk.solve(p, R, start, iters, max_dev=math.inf)
            self._budget -= fk.iterations
            if sol is not None:  # converged: on the seed's branch or continuing last cycle's, else no
                if _near(sol, seed) or (last is not None and _near(sol, last)):
                    self._warm[kind] = sol
                    return sol
                break
        what = "TCP target" if kind == "tcp" else "target projected onto the workspace"
        self._rep("ik_fallback", now, value=float(self.ik_budget - self._budget), limit=float(self.ik_budget),
                  message=f"{what}: no IK solution near its branch within the Newton budget (iterations); "
                          "stop policy (brake, then hold) instead")
        return None

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


def _near(q, ref) -> bool:
    for i in range(6):
        d = q[i] - ref[i]
        if d > IK_MAX_DEV or d < -IK_MAX_DEV:
            return False
    return True


def _dist(p, p2) -> float:
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(p, p2)))


__all__ = ["TargetShaper", "IK_ITERS", "IK_BUDGET", "IK_MAX_DEV"]
