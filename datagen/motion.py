"""Joint-space planning (OMPL RRTConnect + shortcutting), straight Cartesian moves, time parameterization.

Every trajectory leaves here sampled at the physics step (2 ms), collision-checked at that resolution, and
within the joint velocity / acceleration / jerk and TCP linear / angular speed limits by finite differences
of the samples themselves (at rest before and after), i.e. what the runtime's safety filter computes from
the servo targets; `safety.harness.check_stream` accepts them unchanged.

Time parameterization: a planned joint path is a polyline; each leg gets a synchronized, jerk-limited
trapezoidal profile from rest to rest (a joint-space corner cannot be taken at speed with bounded
acceleration). A Cartesian move is a C2 joint curve (IK at knots 5 mm apart, a natural cubic spline
between them) timed by one such profile along it. Where the sampled trajectory still exceeds a limit, the
whole move is slowed by one common factor and re-sampled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from sim.kinematics import UnreachableError, matrix_to_rotvec, rotvec_to_matrix

ou.setLogLevel(ou.LOG_NONE)  # OMPL logs through its own handler; failures are raised as PlanningFailed


class PlanningFailed(RuntimeError):
    """No collision-free, reachable trajectory was found; the message says which step failed and why."""


@dataclass(frozen=True)
class Limits:
    velocity: np.ndarray  # rad/s per joint
    acceleration: np.ndarray  # rad/s^2 per joint
    jerk: np.ndarray  # rad/s^3 per joint
    tcp_speed: float  # m/s
    tcp_acceleration: float  # m/s^2 (along the path)
    tcp_angular_speed: float  # rad/s


# Planning defaults: demonstrations move at a pace a 10 Hz policy can imitate, well inside the hardware limits.
_DEFAULTS = dict(velocity=1.0, acceleration=2.0, jerk=100.0, tcp_speed=0.25, tcp_acceleration=1.0,
                 tcp_angular_speed=1.0)
_MARGIN = 0.9  # plan at 90 % of a hard cap, so tracking overshoot never trips the safety monitor


def motion_limits(variant) -> Limits:
    """The limits trajectories are timed for: min(planning defaults, 90 % of the safety layer's caps).

    The caps come from `safety.limits.default_limits` when it is importable, else from the variant's maximum
    joint velocity and the collaborative 0.25 m/s TCP speed. One function, so the lead can switch the source.
    """
    d = _DEFAULTS
    vel, acc, jerk = (np.full(6, d[k]) for k in ("velocity", "acceleration", "jerk"))
    vel = np.minimum(vel, _MARGIN * np.asarray(variant.max_joint_velocity, dtype=float))
    tcp, ang = _MARGIN * d["tcp_speed"], _MARGIN * d["tcp_angular_speed"]
    try:
        from safety.limits import default_limits
    except ImportError:
        default_limits = None
    if default_limits is not None:
        lim = default_limits(variant.name)
        vel = np.minimum(vel, _MARGIN * np.asarray(lim.joints.velocity, dtype=float))
        acc = np.minimum(acc, _MARGIN * np.asarray(lim.joints.acceleration, dtype=float))
        jerk = np.minimum(jerk, _MARGIN * np.asarray(lim.joints.jerk, dtype=float))
        tcp = min(tcp, _MARGIN * float(lim.tcp.max_linear_speed))
        ang = min(ang, _MARGIN * float(lim.tcp.max_angular_speed))
    return Limits(vel, acc, jerk, tcp, d["tcp_acceleration"], ang)


def trapezoid(length: float, v: float, a: float, dt: float, j: float = np.inf) -> np.ndarray:
    """Positions (0..length) at t = 0, dt, ..., T of a rest-to-rest profile with |v| <= v, |a| <= a.

    T is rounded up to whole steps by slowing the profile, which keeps it within both limits. A finite jerk
    limit j smooths it with a moving average over 2a/j: velocity and acceleration stay within their limits
    (averages of bounded values) and the acceleration, which steps by at most 2a, now ramps at <= j.
    """
    if length <= 1e-12:
        return np.zeros(1)
    T = length / v + v / a if length >= v * v / a else 2.0 * np.sqrt(length / a)
    n = max(2, int(np.ceil(T / dt - 1e-9)))
    f = n * dt / T
    v, a = v / f, a / f**2
    t = np.arange(n + 1) * dt
    ta = v / a if length >= v * v / a else np.sqrt(length / a)  # end of acceleration
    T = n * dt
    s = np.where(t < ta, 0.5 * a * t**2, 0.5 * a * ta**2 + a * ta * (t - ta))
    s = np.where(t > T - ta, length - 0.5 * a * np.maximum(T - t, 0.0) ** 2, s)
    s[-1] = length
    s = np.clip(s, 0.0, length)
    w = int(np.ceil(2.0 * a / (j * dt))) if np.isfinite(j) else 1
    if w > 1:
        padded = np.concatenate([np.zeros(w - 1), s, np.full(w - 1, length)])
        c = np.concatenate([[0.0], np.cumsum(padded)])
        s = (c[w:] - c[:-w]) / w
        s[0], s[-1] = 0.0, length
    return s


def _rest_fd(Q: np.ndarray, dt: float):
    """Velocity, acceleration, jerk of a stream at rest before and after (as the safety monitor sees it)."""
    P = np.concatenate([Q[:1], Q[:1], Q, Q[-1:], Q[-1:]])
    V = np.diff(P, axis=0) / dt
    A = np.diff(V, axis=0) / dt
    return V, A, np.diff(A, axis=0) / dt


def limit_ratio(Q: np.ndarray, dt: float, limits: Limits, kin) -> float:
    """How far a sampled trajectory exceeds its limits, by finite differences (<= 1: within all of them).

    Velocity ratios count linearly, accelerations by their square root and jerks by their cube root: the
    factor by which slowing the whole trajectory down would bring each within its limit.
    """
    if len(Q) < 2:
        return 0.0
    V, A, J = _rest_fd(np.asarray(Q, float), dt)
    T = kin.fk_batch(Q)
    tcp = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt
    Rrel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    ang = np.arccos(np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)) / dt
    return float(max(np.max(np.abs(V) / limits.velocity), np.sqrt(np.max(np.abs(A) / limits.acceleration)),
                     np.cbrt(np.max(np.abs(J) / limits.jerk)), np.max(tcp) / limits.tcp_speed,
                     np.max(ang) / limits.tcp_angular_speed))


def _spline(u: np.ndarray, K: np.ndarray):
    """Natural cubic spline through knots K (n, 6) at uniform u: C2, so its jerk along a timing is bounded."""
    n, h = len(u), u[1] - u[0]
    M = np.zeros_like(K)
    if n > 2:
        A = np.diag(np.full(n - 2, 4.0)) + np.diag(np.ones(n - 3), 1) + np.diag(np.ones(n - 3), -1)
        M[1:-1] = np.linalg.solve(A, 6.0 / h**2 * (K[2:] - 2 * K[1:-1] + K[:-2]))

    def at(x):
        i = np.clip(((x - u[0]) / h).astype(int), 0, n - 2)
        a, b = (u[i + 1] - x)[:, None] / h, (x - u[i])[:, None] / h
        return (a * K[i] + b * K[i + 1] + ((a**3 - a) * M[i] + (b**3 - b) * M[i + 1]) * h**2 / 6.0)

    return at


class MotionPlanner:
    """Plans and times arm motions against a CollisionChecker; all randomness comes from the caller's rng."""

    def __init__(self, checker, kin, limits: Limits, dt: float, check_res: float = 0.01):
        self.checker, self.kin, self.limits, self.dt = checker, kin, limits, dt
        self.check_res = check_res  # rad: collision-check spacing along joint paths (L-inf)

    # -- collision checking of sampled trajectories --------------------------------------------------------
    def first_collision(self, Q, res: float | None = None, **kw) -> int:
        """Index of the first sample in collision, checking samples at most `res` rad apart; -1 if none."""
        res = self.check_res if res is None else res
        step = np.max(np.abs(np.diff(Q, axis=0)), axis=1) if len(Q) > 1 else np.zeros(0)
        acc = np.concatenate([[0.0], np.cumsum(step)])
        idx = np.unique(np.concatenate([np.searchsorted(acc, np.arange(0.0, acc[-1], res)), [len(Q) - 1]]))
        for i in idx:
            if not self.checker.is_free(Q[i], **kw):
                return int(i)
        return -1

    def _require_free(self, Q, what: str, res: float | None = None, **kw) -> None:
        i = self.first_collision(Q, res, **kw)
        if i >= 0:
            hits = self.checker.collisions(Q[i], **kw)
            raise PlanningFailed(f"{what}: collision at sample {i}/{len(Q)}: {hits[:3]}")

    # -- joint-space planning ----------------------------------------------------------------------------------
    def plan(self, q0, q1, rng: np.random.Generator, budget: float = 2.0, pad: float = 1.0,
             **kw) -> np.ndarray:
        """Collision-free joint waypoints (K, 6) from q0 to q1 (the straight line when it is free).

        kw go to the checker (held, gripper, allow, clearance). RRTConnect in the box spanned by q0, q1
        padded by `pad` rad (within joint limits), seeded from rng; the path is shortcut with OMPL's
        PathSimplifier (simplifyMax: no time limit, hence reproducible).
        """
        q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
        for q, name in ((q0, "start"), (q1, "goal")):
            if not self.checker.is_free(q, **kw):
                raise PlanningFailed(f"{name} configuration in collision: {self.checker.collisions(q, **kw)[:3]}")
        if self.first_collision(np.linspace(q0, q1, 2 + int(np.max(np.abs(q1 - q0)) / 0.005)), **kw) < 0:
            return np.stack([q0, q1])
        ou.RNG.setSeed(int(rng.integers(1, 2**31 - 1)))
        space = ob.RealVectorStateSpace(6)
        bounds = ob.RealVectorBounds(6)
        lo = np.maximum(self.kin.lower, np.minimum(q0, q1) - pad)
        hi = np.minimum(self.kin.upper, np.maximum(q0, q1) + pad)
        for j in range(6):
            bounds.setLow(j, float(lo[j]))
            bounds.setHigh(j, float(hi[j]))
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        checker = self.checker
        ss.setStateValidityChecker(lambda s: checker.is_free([s[0], s[1], s[2], s[3], s[4], s[5]], **kw))
        si = ss.getSpaceInformation()
        si.setStateValidityCheckingResolution(self.check_res / max(si.getMaximumExtent(), 1e-6))
        ss.setPlanner(og.RRTConnect(si))
        start, goal = space.allocState(), space.allocState()
        for j in range(6):
            start[j], goal[j] = float(q0[j]), float(q1[j])
        ss.setStartAndGoalStates(start, goal)
        status = ss.solve(budget)
        if not ss.haveExactSolutionPath():
            raise PlanningFailed(f"RRTConnect found no path in {budget:.1f} s ({status.asString()})")
        ss.simplifySolution(0.0)
        W = np.array([[s[j] for j in range(6)] for s in ss.getSolutionPath().getStates()])
        W[0], W[-1] = q0, q1
        return W

    def _retime(self, build, what: str) -> np.ndarray:
        """Sample build(scale) and slow it by one common factor until its finite differences fit the limits."""
        scale = 1.0
        for _ in range(6):
            Q = build(scale)
            r = limit_ratio(Q, self.dt, self.limits, self.kin)
            if r <= 1.0 + 1e-9:
                return Q
            scale *= 0.97 / r
        raise PlanningFailed(f"{what}: time parameterization cannot meet the limits (near a singularity?)")

    def time_path(self, W) -> np.ndarray:
        """Sample a joint polyline at dt: synchronized jerk-limited trapezoids per leg, at rest at waypoints."""
        W = np.asarray(W, float)
        lim = self.limits
        legs = []
        for a, b in zip(W[:-1], W[1:]):
            d = b - a
            ad = np.abs(d) + 1e-12
            T = self.kin.fk_batch(a + np.linspace(0, 1, 12)[:, None] * d)
            dp = np.max(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)) * 11 * 1.05 + 1e-9
            Rrel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
            dth = np.max(np.arccos(np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1))) * 11 * 1.05 + 1e-9
            legs.append((a, d, min(np.min(lim.velocity / ad), lim.tcp_speed / dp, lim.tcp_angular_speed / dth),
                         min(np.min(lim.acceleration / ad), lim.tcp_acceleration / dp), np.min(lim.jerk / ad)))

        def build(k):
            parts = [W[:1]] + [a + trapezoid(1.0, k * v, k * k * acc, self.dt, k**3 * j)[1:, None] * d
                               for a, d, v, acc, j in legs]
            return np.concatenate(parts)

        return self._retime(build, "joint path")

    def joint_move(self, q0, q1, rng, budget: float = 2.0, **kw) -> np.ndarray:
        """Plan, time and verify a joint-space move; retries planning when the dense check finds a graze."""
        last = None
        for _ in range(3):
            Q = self.time_path(self.plan(q0, q1, rng, budget, **kw))
            try:
                self._require_free(Q, "planned path", **kw)
                return Q
            except PlanningFailed as err:
                last = err
        raise last

    # -- Cartesian moves -----------------------------------------------------------------------------------------
    def cartesian(self, q0, pose_fn, length: float, knot: float = 0.005, tcp_speed: float | None = None,
                  **kw) -> np.ndarray:
        """Follow TCP poses pose_fn(u), u in [0, 1], `length` metres of TCP travel, from q0; sampled at dt.
        `tcp_speed` (m/s) caps this move's TCP speed below the limits' (a careful approach to a contact).

        IK at knots every `knot` metres, each seeded with the previous solution (the branch q0 is on); a
        jump between knots means a singularity or branch change and fails the move.
        """
        q0 = np.asarray(q0, float)
        n = max(4, int(np.ceil(length / knot)) + 1)
        u = np.linspace(0.0, 1.0, n)
        K = np.empty((n, 6))
        K[0] = q = q0
        for i in range(1, n):
            try:
                q = self.kin.ik(pose_fn(u[i]), q)
            except UnreachableError as err:
                raise PlanningFailed(f"Cartesian move leaves the workspace at {u[i]:.0%}: {err}") from None
            if np.max(np.abs(q - K[i - 1])) > 0.25:
                raise PlanningFailed(f"Cartesian move crosses a singularity or IK branch at {u[i]:.0%}")
            K[i] = q
        lim = self.limits
        P = np.array([pose_fn(x) for x in u])
        L = float(np.sum(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1))) + 1e-9
        Rrel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
        th = float(np.sum(np.arccos(np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1)))) + 1e-9
        dqdu = np.max(np.abs(np.gradient(K, u, axis=0)), axis=0) * 1.1 + 1e-9
        vmax = lim.tcp_speed if tcp_speed is None else min(lim.tcp_speed, tcp_speed)
        vu = min(np.min(lim.velocity / dqdu), vmax / L, lim.tcp_angular_speed / th)
        au = min(np.min(lim.acceleration / dqdu), lim.tcp_acceleration / L)
        ju = np.min(lim.jerk / dqdu)
        curve = _spline(u, K)
        Q = self._retime(lambda k: curve(trapezoid(1.0, k * vu, k * k * au, self.dt, k**3 * ju)), "Cartesian move")
        Q[0] = q0
        self._require_free(Q, "Cartesian move", res=0.002, **kw)
        return Q

    def line(self, q0, T_goal, **kw) -> np.ndarray:
        """Straight TCP line from fk(q0) to T_goal, orientation slerped; sampled at dt and checked."""
        T0 = self.kin.fk(q0)
        T1 = np.asarray(T_goal, float)
        dp = T1[:3, 3] - T0[:3, 3]
        rv = matrix_to_rotvec(T0[:3, :3].T @ T1[:3, :3])

        def pose(u):
            T = np.eye(4)
            T[:3, :3] = T0[:3, :3] @ rotvec_to_matrix(u * rv)
            T[:3, 3] = T0[:3, 3] + u * dp
            return T

        return self.cartesian(q0, pose, float(np.linalg.norm(dp)) + 0.05 * float(np.linalg.norm(rv)), **kw)
