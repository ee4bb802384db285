"""Closed-loop harness: feed a command stream through a SafetyFilter with a simulated arm, check the output.

The simulated arm is an ideal joint integrator with a delay: the measured joints are the command sent
`delay` cycles ago (a UR's servoJ tracks within milliradians; a delay is what the filter sees). `check_stream`
measures what the robot would see, by finite differences of the commanded positions, against the limits.

Tolerance (TOL_REL, round-off floor): a limit holds when value <= limit * (1 + 1e-9) + floor, where floor is
the round-off of an n-th finite difference of positions of magnitude |q|: 4 eps max(1, |q|) (2 / dt)^n
(n = 0 position, 1 velocity, 2 acceleration, 3 jerk). At 500 Hz that is ~6e-6 rad/s^3 on the jerk, 4e-8 of
the default 150 rad/s^3. The filter shrinks its limits by 1e-6 relative inside, so it never needs the tolerance
beyond round-off. Cartesian limits (box, table plane, keep-out boxes) hold to 1e-9 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

TOL_REL = 1e-9
TOL_M = 1e-9


@dataclass
class Command:
    """One cycle's input: a joint target (or None), a TCP target (or None) and its time stamp."""

    q: object = None
    command_time: float = 0.0
    tcp: object = None
    estop: bool = False
    reset_operator: str | None = None  # e-stop reset by this operator before the step


@dataclass
class StreamResult:
    q: np.ndarray  # (N + 1, 6): the initial measured joints, then each cycle's output
    modes: list = field(default_factory=list)
    states: list = field(default_factory=list)
    events: list = field(default_factory=list)
    resynced: list = field(default_factory=list)


def run_stream(filt, q0, commands, dt: float | None = None, delay: int = 1, t0: float = 0.0) -> StreamResult:
    """Run `commands` (a list of Command) through `filt`, starting at rest at q0; now = t0 + k dt."""
    dt = filt.dt if dt is None else dt
    q0 = np.asarray(q0, dtype=float)
    sent = [q0]
    res = StreamResult(q=None)
    for k, c in enumerate(commands):
        now = t0 + k * dt
        if c.estop:
            filt.estop(now, "test")
        if c.reset_operator is not None:
            filt.reset_estop(now, c.reset_operator)
        measured = sent[max(0, len(sent) - 1 - delay)]
        r = filt.step(c.q, measured, None, now, c.command_time, desired_tcp=c.tcp)
        sent.append(r.q)
        res.modes.append(r.mode)
        res.states.append(r.state)
        res.events.extend(r.events)
        res.resynced.append(r.resynced)
    res.q = np.array(sent)
    return res


def finite_differences(Q: np.ndarray, dt: float):
    """Velocity, acceleration, jerk of a position stream that starts at rest (v = a = 0 before Q[0])."""
    Q = np.asarray(Q, dtype=float)
    V = np.diff(Q, axis=0, prepend=Q[:1]) / dt  # v_0 = 0
    A = np.diff(V, axis=0, prepend=V[:1]) / dt  # a_0 = 0
    Jk = np.diff(A, axis=0, prepend=A[:1]) / dt
    return V, A, Jk


def check_stream(Q, dt: float, limits, fk=None, workspace=None) -> list[str]:
    """Violations of the joint (and, with fk + workspace, Cartesian) limits by the stream; [] if none."""
    Q = np.asarray(Q, dtype=float)
    j = limits.joints
    lo, hi = np.array(j.soft_lower), np.array(j.soft_upper)
    scale = max(1.0, float(np.abs(Q).max()))
    eps = 4.0 * np.finfo(float).eps * scale
    floor = [eps * (2.0 / dt) ** n for n in range(4)]
    out = []
    if np.any(Q < lo - TOL_REL * np.abs(lo) - floor[0]) or np.any(Q > hi + TOL_REL * np.abs(hi) + floor[0]):
        k, i = np.argwhere((Q < lo - 1e-12) | (Q > hi + 1e-12))[0]
        out.append(f"position: joint {i} = {Q[k, i]} outside [{lo[i]}, {hi[i]}] at cycle {k}")
    V, A, Jk = finite_differences(Q, dt)
    for name, X, lim, n in (("velocity", V, j.velocity, 1), ("acceleration", A, j.acceleration, 2),
                            ("jerk", Jk, j.jerk, 3)):
        lim = np.array(lim)
        bad = np.abs(X) > lim * (1 + TOL_REL) + floor[n]
        if bad.any():
            k, i = np.argwhere(bad)[0]
            out.append(f"{name}: joint {i} = {X[k, i]} beyond {lim[i]} at cycle {k} (max ratio "
                       f"{float(np.max(np.abs(X) / lim)):.12g})")
    if fk is not None and workspace is not None:
        for k, q in enumerate(Q):
            px, py, pz, R = fk.pose(q.tolist())
            pts = workspace.points((px, py, pz), R)
            s = workspace.min_slack(pts)
            if s < -TOL_M:
                out.append(f"workspace: slack {s} m at cycle {k}")
                break
    return out


def stop_within(Q, k0: int, dt: float, limiter) -> list[str]:
    """The stream, stopping from cycle k0 on, stays within the stop bound of its state at k0 and rests."""
    V, A, _ = finite_differences(Q, dt)
    out = []
    for i in range(Q.shape[1]):
        dp = limiter.stop_bound(i, V[k0, i], A[k0, i])
        dm = limiter.stop_bound(i, -V[k0, i], -A[k0, i])
        d = Q[k0:, i] - Q[k0, i]
        if d.max() > dp + 1e-12 or -d.min() > dm + 1e-12:
            out.append(f"joint {i} travelled [{d.min()}, {d.max()}] beyond its stop bound [-{dm}, {dp}]")
    if np.any(V[-1] != 0.0) or np.any(Q[-1] != Q[-2]):
        out.append(f"not at rest at the end: v = {V[-1]}")
    return out


def tcp_speeds(Q, dt: float, fk) -> tuple[np.ndarray, np.ndarray]:
    """Linear (m/s) and angular (rad/s) TCP speed of each step of the stream."""
    from safety.fastfk import rotation_angle

    poses = [fk.pose(q.tolist()) for q in np.asarray(Q)]
    lin = np.array([math.dist(a[:3], b[:3]) / dt for a, b in zip(poses, poses[1:])])
    ang = np.array([rotation_angle(a[3], b[3]) / dt for a, b in zip(poses, poses[1:])])
    return lin, ang


__all__ = ["Command", "StreamResult", "run_stream", "check_stream", "finite_differences", "stop_within",
           "tcp_speeds", "TOL_REL", "TOL_M"]
