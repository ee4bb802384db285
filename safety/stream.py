"""The commanded stream: what the filter has sent and where that puts the arm.

Every limit is enforced on this stream: the positions q sent every dt, their velocity v = (q' - q) / dt and
acceleration a = (v' - v) / dt (finite differences, exactly what the robot sees), whatever comes in. With
the position it keeps what the per-cycle checks need about the current output: the TCP pose, the
workspace points (TCP and finger points) and their slack, and, on demand, the joint frames (axes and
origins, for the Jacobian terms of the braking check), computed at most once per cycle.

FK is cached: a pose the chain already computed this cycle for exactly the joints it then sends (the TCP
speed checks evaluate the next output's pose) is not computed again for the new output.
"""

from __future__ import annotations


class CommandedStream:
    def __init__(self, dt: float, velocity, fk, workspace):
        self.dt = dt
        self.V = list(velocity)
        self.fk = fk
        self.workspace = workspace
        self.q: list | None = None  # None until the first measurement
        self.v: list = [0.0] * 6
        self.a: list = [0.0] * 6
        self.prev_target: list | None = None  # the target followed last cycle (None: stopping / restarting)
        self.pose = self.pts = None
        self.slack = 0.0
        self._frames = None
        self._memo_q = self._memo_pose = self._memo_q2 = self._memo_pose2 = None

    def reset(self, q: list, qd: list | None = None) -> None:
        """Restart from joints q (6 floats), at rest unless qd is given (clipped to the velocity limits)."""
        V = self.V
        self.q = q
        self.v = [0.0] * 6 if qd is None else [max(-V[i], min(V[i], qd[i])) for i in range(6)]
        self.a = [0.0] * 6
        self.prev_target = None
        self._set_pose(q)

    def advance(self, qn: list, pose=None, pts=None, slack=None) -> tuple[list, list]:
        """Send qn: the new velocity and acceleration by finite differences; pose/pts/slack if known."""
        q, v, dt = self.q, self.v, self.dt
        vn = [(qn[i] - q[i]) / dt for i in range(6)]
        an = [(vn[i] - v[i]) / dt for i in range(6)]
        self.q, self.v, self.a = qn, vn, an
        self._set_pose(qn, pose, pts, slack)
        return vn, an

    def refresh_points(self) -> None:
        """The workspace points and slack of the current output again (after its finger points moved)."""
        if self.pose is not None:
            self.pts, self.slack = self.workspace.at(self.pose)

    def _set_pose(self, q, pose=None, pts=None, slack=None) -> None:
        if pose is None:
            pose = self.pose_of(q)
            pts, slack = self.workspace.at(pose)
        self.pose, self.pts, self.slack = pose, pts, slack
        self._frames = None

    # ---- kinematics of the current output and of candidates ------------------------------------------
    def pose_of(self, q):
        """fk.pose(q), reusing one of the last two poses computed through here for the same list of floats."""
        if q == self._memo_q:
            return self._memo_pose
        if q == self._memo_q2:
            return self._memo_pose2
        pose = self.fk.pose(q)
        self._memo_q2, self._memo_pose2 = self._memo_q, self._memo_pose
        self._memo_q, self._memo_pose = list(q), pose  # a copy: callers may reuse their list
        return pose

    def frames(self):
        """fk.frames of the current output, computed once per cycle (the same object on every call)."""
        fr = self._frames
        if fr is None:
            fr = self._frames = self.fk.frames(self.q)
        return fr


__all__ = ["CommandedStream"]
