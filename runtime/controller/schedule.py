"""The timeline of future joint targets: which chunk is in effect at each time, and how a new one takes over.

Why timestamps and not queues: every action carries the absolute time at which it should take effect, so the
controller samples the timeline at the servo clock instead of popping actions at its own pace; a chunk that
arrives late is simply entered part way (its past actions are dropped but the last past one anchors the
spline), and an early one waits for its first action time.

Times are float seconds on the host monotonic clock, in *target time*: the loop samples the timeline at
now + execution_latency, so each target is commanded that much before it should be reached.

Takeover: the new chunk's spline starts at its first kept knot with the chunk's own velocity there, and a
smoothstep blend from the old trajectory to it starts at max(now + latency, first knot time). The blend
lasts `blend_time`, lengthened when the two trajectories differ so much that the blend's own derivatives
(w''' dp + 3 w'' dv + 3 w' da for jerk, and likewise for acceleration and velocity) would use more than
`budget` of a joint's limit; the safety filter remains the backstop beyond `max_blend_time`.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from runtime.controller.ik_follow import ChunkRejected, JointChunk, first_kept
from runtime.controller.interpolate import W1_MAX, W2_MAX, W3_MAX, Blend, Hold, Spline


class Timeline:
    def __init__(self, config, joint_limits):
        self.cfg = config
        self.V = np.asarray(joint_limits.velocity, dtype=float)
        self.A = np.asarray(joint_limits.acceleration, dtype=float)
        self.J = np.asarray(joint_limits.jerk, dtype=float)
        self.traj = None  # None: no trajectory (the loop holds); else Hold | Spline | Blend | StopCurve
        self.chunk: JointChunk | None = None  # the newest adopted chunk
        self.end_time = -math.inf  # target time of the newest chunk's last action (s)
        self._gt: list[float] = []  # gripper channel: times and values (zero-order hold)
        self._gv: list[float] = []
        self.last_blend = 0.0  # duration of the latest blend (s), for telemetry/tests
        self.last_dropped = 0  # past actions dropped from the latest chunk

    # ---- queries --------------------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        return self.traj is not None

    def reference(self, t: float, fallback) -> np.ndarray:
        """Joint target at target time t (the IK seed of a new chunk); `fallback` when nothing is planned."""
        traj = self.traj  # read once: another thread may replace it meanwhile
        return np.array(traj.eval(t)[0]) if traj is not None else np.asarray(fallback, dtype=float)

    def sample(self, t: float):
        """(p, v, a) at target time t; collapses finished blends. None when no trajectory is set."""
        if self.traj is None:
            return None
        self.traj = self.traj.settled(t)
        return self.traj.eval(t)

    def gripper(self, t: float) -> float | None:
        """The gripper channel in effect at t: the newest action at or before t (the first if t precedes it)."""
        if not self._gt:
            return None
        return self._gv[max(0, bisect.bisect_right(self._gt, t) - 1)]

    # ---- changes --------------------------------------------------------------------------------------
    def clear(self) -> None:
        """Forget every chunk (e-stop, protective stop, recovery): nothing planned is still valid."""
        self.traj, self.chunk, self.end_time = None, None, -math.inf
        self._gt, self._gv = [], []

    def set(self, traj, end_time: float | None = None) -> None:
        """Replace the trajectory outright (a hold or the controlled stop)."""
        self.traj = traj
        if end_time is not None:
            self.end_time = end_time

    def adopt(self, jc: JointChunk, t_eval: float, hold_q) -> int:
        """Make `jc` the plan from t_eval on, blending from the current trajectory (or a hold at `hold_q`).
        Returns how many of the chunk's actions were dropped as past (before the anchor). Raises
        ChunkRejected if the chunk went stale since it was converted."""
        times = list(jc.times)
        if times[-1] < t_eval:
            raise ChunkRejected("chunk_stale", "every action was in the past by the time the chunk could start")
        k0 = first_kept(times, t_eval)  # trim again: conversion happened a little earlier
        times, q, grip = times[k0:], jc.q[k0:], jc.gripper[k0:]
        old = self.traj if self.traj is not None else Hold(hold_q)
        old = old.settled(t_eval)
        new = Spline(times, q)
        t_b = max(t_eval, times[0])
        T = self.blend_duration(old, new, t_b)
        self.traj = Blend(old, new, t_b, T)
        self.chunk, self.end_time, self.last_blend = jc, times[-1], T
        self.last_dropped = jc.dropped + k0
        # gripper: the old channel until the new chunk's first action, then the new one
        keep = bisect.bisect_left(self._gt, times[0])
        gt, gv = self._gt[:keep], self._gv[:keep]
        cut = max(0, bisect.bisect_right(gt, t_eval) - 1)  # drop what is long past, keep the value in effect
        self._gt = gt[cut:] + [float(t) for t in times]
        self._gv = gv[cut:] + [float(g) for g in grip]
        return self.last_dropped

    def blend_duration(self, old, new, t_b: float) -> float:
        """Shortest duration >= blend_time for which the blend's own derivatives stay within budget."""
        cfg = self.cfg
        beta = cfg.budget
        T = cfg.blend_time
        p0, v0, a0 = old.eval(t_b)
        p1, v1, a1 = new.eval(t_b)
        dv, da = np.abs(v1 - v0), np.abs(a1 - a0)
        D = np.abs(p1 - p0)
        while True:
            for t in (t_b + 0.5 * T, t_b + T):  # the offset over the window, not only at its start
                D = np.maximum(D, np.abs(new.eval(t)[0] - old.eval(t)[0]))
            jerk = W3_MAX * D / T ** 3 + 3.0 * W2_MAX * dv / T ** 2 + 3.0 * W1_MAX * da / T
            acc = W2_MAX * D / T ** 2 + 2.0 * W1_MAX * dv / T  # (w (a1 - a0) and w (v1 - v0) stay within
            vel = W1_MAX * D / T  # the trajectories' own range: no window length changes them)
            if (np.all(jerk <= beta * self.J) and np.all(acc <= beta * self.A) and np.all(vel <= beta * self.V)) \
                    or T >= cfg.max_blend_time:
                return min(T, cfg.max_blend_time)
            T *= 1.25


__all__ = ["Timeline"]
