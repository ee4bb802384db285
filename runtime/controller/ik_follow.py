"""ActionChunk -> joint knots: the analytic IK on the arm's current branch, continuity-checked.

Why in joint space and why checked here: the safety filter, the servo and the spline all work on joints, and
blending two chunks is only meaningful if both are on the same IK branch. `Kinematics.ik` picks the solution
nearest the seed; seeding each knot with the previous one follows the branch the arm is on. When the target
leaves that branch's reach (the nearest solution is another elbow/wrist/shoulder configuration) or leaves
the arm's reach, the chunk is rejected as a whole (ChunkRejected -> an event; the loop keeps the old tail):
half a chunk, or a branch flip executed as a fast joint swing, is worse than finishing the old plan.

Checks, per chunk: every target finite with a valid rotation; IK exists and reproduces the pose (a solution
clipped at a joint limit does not); the first knot within `max_start_offset` of the trajectory the arm is
following at that time; each knot-to-knot step within jump_factor x velocity limit x interval + jump_slack
(a branch flip needs several rad in 0.1 s). Joint chunks ("joint" kind) get the same continuity checks.
"""

from __future__ import annotations

import bisect
import math
import time
from dataclasses import dataclass

import numpy as np

from datagen.schema import rot6d_to_matrix
from sim.kinematics import Kinematics, UnreachableError, wrap_angle
from sim.robot import TCP_OFFSET_Z


class ChunkRejected(ValueError):
    """A chunk that cannot be executed; `kind` is the event kind, `index` the offending action (or None)."""

    def __init__(self, kind: str, message: str, index: int | None = None):
        super().__init__(message)
        self.kind, self.index = kind, index


@dataclass(frozen=True)
class JointChunk:
    """A chunk converted to joints: the knots still worth executing (past ones trimmed to one anchor)."""

    times: tuple  # float seconds, host monotonic, strictly increasing
    q: np.ndarray  # (N, 6) rad
    gripper: np.ndarray  # (N,) 0 open .. 1 closed
    obs_time: float  # s
    dropped: int  # actions dropped as past (before the anchor)
    branch: tuple | None  # (shoulder, wrist, elbow) of the knots (EE chunks)


def first_kept(times, t_eval: float) -> int:
    """Index of the first action to keep at t_eval: the last one at or before t_eval anchors the spline."""
    return max(0, bisect.bisect_right(times, t_eval) - 1)


def branch_of(kin: Kinematics, q) -> tuple[int, int, int]:
    """IK branch (shoulder, wrist, elbow), 0/1 each, as indexed by `Kinematics.ik_all` (4 s + 2 w + e)."""
    q = np.asarray(q, dtype=float)
    F = kin.fk_flange(q)
    wc = F[:3, 3] - kin.d[5] * F[:3, 2]  # wrist centre
    phi = math.atan2(wc[1], wc[0])
    shoulder = 0 if float(wrap_angle(q[0] - phi - math.pi / 2)) >= 0.0 else 1
    return shoulder, 0 if math.sin(q[4]) >= 0.0 else 1, 0 if math.sin(q[2]) >= 0.0 else 1


class ChunkConverter:
    def __init__(self, variant: str, config, velocity_limits):
        self.kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
        self.cfg = config
        self.vel = np.asarray(velocity_limits, dtype=float)

    def convert(self, chunk, t_eval: float, reference) -> JointChunk:
        """Trim past actions at `t_eval` (s) and convert; `reference(t)` is the joint trajectory the arm
        follows (the seed of the first knot). Raises ChunkRejected."""
        times = [int(x) * 1e-9 for x in np.asarray(chunk.times_ns)]
        acts = np.asarray(chunk.actions, dtype=float)
        if not times or acts.ndim != 2 or acts.shape[0] != len(times):
            raise ChunkRejected("chunk_malformed", "actions and times_ns must have one row per action")
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ChunkRejected("chunk_malformed", "action times must strictly increase")
        if not np.all(np.isfinite(acts)):
            raise ChunkRejected("chunk_malformed", "actions contain NaN/Inf")
        if times[-1] < t_eval:
            raise ChunkRejected("chunk_stale", f"every action is in the past (last {t_eval - times[-1]:.3f} s "
                                               "before the execution time)")
        k0 = first_kept(times, t_eval)
        times, acts = times[k0:], acts[k0:]
        seed = np.asarray(reference(times[0]), dtype=float)
        branch = None
        if chunk.kind == "joint":
            if acts.shape[1] != 7:
                raise ChunkRejected("chunk_malformed", f"joint chunk needs 7 values per action, got {acts.shape[1]}")
            q = acts[:, :6].copy()
        elif chunk.kind == "ee":
            if acts.shape[1] != 10:
                raise ChunkRejected("chunk_malformed", f"EE chunk needs 10 values per action, got {acts.shape[1]}")
            q, branch = self._ik(acts, seed, k0)
        else:
            raise ChunkRejected("chunk_malformed", f"unknown chunk kind {chunk.kind!r}")
        self._check_continuity(q, times, seed, k0)
        grip = np.clip(acts[:, -1], 0.0, 1.0)
        return JointChunk(tuple(times), q, grip, int(chunk.obs_time_ns) * 1e-9, k0, branch)

    def _ik(self, acts, seed, k0):
        kin, tol = self.kin, self.cfg.ik_tolerance
        start = prev_b = branch_of(kin, seed)
        out = np.empty((len(acts), 6))
        prev = seed
        for k, a in enumerate(acts):
            idx = k0 + k
            with np.errstate(all="ignore"):
                R = rot6d_to_matrix(a[3:9])
            if not np.all(np.isfinite(R)):
                raise ChunkRejected("chunk_malformed", f"action {idx}: the 6-D rotation is degenerate", idx)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, a[:3]
            try:
                q = kin.ik(T, prev)
            except UnreachableError as exc:
                raise ChunkRejected("chunk_unreachable", f"action {idx}: {exc}", idx) from None
            F = kin.fk(q)
            perr = float(np.linalg.norm(F[:3, 3] - T[:3, 3]))
            rerr = float(np.linalg.norm(F[:3, :3] - R))
            if perr > tol or rerr > 10.0 * tol:
                raise ChunkRejected("chunk_unreachable", f"action {idx}: reachable only beyond a joint limit "
                                                   f"(IK misses by {perr * 1e3:.1f} mm)", idx)
            b = branch_of(kin, q)
            # a branch change with a tiny step is a continuous pass by a singularity; with a big one, a flip
            if b != prev_b and float(np.max(np.abs(q - prev))) > self.cfg.jump_slack:
                raise ChunkRejected("chunk_branch_jump", f"action {idx}: IK leaves branch {prev_b} for {b} "
                                                   f"(joint step {np.max(np.abs(q - prev)):.2f} rad)", idx)
            out[k], prev, prev_b = q, q, b
            time.sleep(0)  # yield the GIL (~2 ms of IK per knot) to the 500 Hz loop thread beside us
        return out, start

    def _check_continuity(self, q, times, seed, k0):
        cfg = self.cfg
        off = np.abs(q[0] - seed)
        if float(off.max()) > cfg.max_start_offset:
            j = int(off.argmax())
            raise ChunkRejected("chunk_joint_jump", f"action {k0}: starts {off[j]:.2f} rad (joint {j}) from the "
                                                    f"current trajectory; allowed {cfg.max_start_offset} rad", k0)
        for k in range(1, len(times)):
            bound = cfg.jump_factor * self.vel * (times[k] - times[k - 1]) + cfg.jump_slack
            step = np.abs(q[k] - q[k - 1])
            if np.any(step > bound):
                j = int(np.argmax(step / bound))
                raise ChunkRejected("chunk_joint_jump", f"action {k0 + k}: joint {j} steps {step[j]:.2f} rad in "
                                                        f"{times[k] - times[k - 1]:.3f} s (allowed {bound[j]:.2f})",
                                    k0 + k)


__all__ = ["ChunkConverter", "ChunkRejected", "JointChunk", "branch_of", "first_kept"]
