"""Time-stamped joint trajectories and their execution on a World at the physics rate.

The primitives return a `Motion` instead of moving the robot themselves, so that the caller decides when
it runs, what observes it (recorder, renderer, success checks) and whether it runs at all. A `Segment` is
one labelled piece with a single gripper command: "move to pre-grasp", "approach", "grasp", "lift"... The
labels become the sub-trajectory boundaries of the recorded data; the gripper command is constant within a
segment because the 2F-85 takes one target per move, as on the real robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Segment:
    """Joint targets `q` (N, 6) at `times` (N,) seconds from the segment's start, with one gripper command.

    `times[0]` is 0 and `q[0]` is where the previous segment ended. Between samples the targets are
    interpolated linearly; planners sample at the physics step, so interpolation only matters for
    hand-written segments (e.g. a two-sample hold).
    """

    times: np.ndarray
    q: np.ndarray
    gripper: float
    label: str

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=float).reshape(-1)
        self.q = np.asarray(self.q, dtype=float).reshape(-1, 6)
        if len(self.times) != len(self.q) or len(self.times) == 0:
            raise ValueError(f"segment {self.label!r}: {len(self.times)} times for {len(self.q)} joint samples")
        if np.any(np.diff(self.times) <= 0):
            raise ValueError(f"segment {self.label!r}: times must increase strictly")

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def steps(self, dt: float) -> int:
        """How many physics steps of `dt` running the segment takes."""
        return int(round(self.duration / dt))

    def targets(self, dt: float) -> np.ndarray:
        """(steps, 6) joint targets, one per physics step, as `execute` commands them."""
        return self.at(self.times[0] + dt * np.arange(1, self.steps(dt) + 1))

    def at(self, t) -> np.ndarray:
        """Joint targets at time(s) t, clamped to the segment: (6,) for a scalar, (len(t), 6) for an array."""
        t = np.asarray(t, dtype=float)
        out = np.column_stack([np.interp(t.reshape(-1), self.times, self.q[:, j]) for j in range(6)])
        return out[0] if t.ndim == 0 else out

    @classmethod
    def hold(cls, q, seconds: float, gripper: float, label: str) -> Segment:
        """Keep the arm at q for `seconds` while the gripper goes to `gripper` (grasp, release)."""
        q = np.asarray(q, dtype=float).reshape(6)
        return cls(np.array([0.0, float(seconds)]), np.stack([q, q]), gripper, label)


@dataclass
class Motion:
    """A sequence of segments, each starting where the previous one ended."""

    segments: list[Segment] = field(default_factory=list)

    @property
    def duration(self) -> float:
        return float(sum(s.duration for s in self.segments))

    @property
    def labels(self) -> list[str]:
        return [s.label for s in self.segments]

    @property
    def final_q(self) -> np.ndarray:
        return self.segments[-1].q[-1].copy()

    def __add__(self, other: Motion) -> Motion:
        return Motion(list(self.segments) + list(other.segments))

    def append(self, seg: Segment) -> None:
        self.segments.append(seg)

    def truncated(self, seconds: float) -> Motion:
        """The motion's first `seconds` (the segment running then is cut at that time)."""
        out, left = [], float(seconds)
        for seg in self.segments:
            if seg.duration <= left:
                out.append(seg)
                left -= seg.duration
                continue
            if left > 0:
                keep = seg.times < seg.times[0] + left
                times = np.append(seg.times[keep], seg.times[0] + left)
                out.append(Segment(times, np.vstack([seg.q[keep], seg.at(times[-1])]), seg.gripper, seg.label))
            break
        return Motion(out)


FINGERS_STILL_S = 0.1  # a hold ends once the fingers have been still this long...
FINGERS_MOST_S = 1.5  # ...or this long after its planned end


def execute(world, motion: Motion, observer=None, offsets: np.ndarray | None = None) -> None:
    """Run `motion` on `world` at the physics rate: one joint target and one mj_step per 2 ms.

    The gripper command is set at the start of each segment. `observer(world, label)` is called after
    every physics step with the running segment's label (recorders subsample it to their own rate).
    `offsets` (steps, 6), one row per physics step (datagen.dart), are added to the commanded joints; the
    observer is then called as `observer(world, label, planned)` with the planned joints, what to record
    as the action.

    With a finger drive on the world (`world.drive_fingers`), the fingers move at the driver's speed: a hold
    (grasp, release) lasts past its planned time until they have stopped, as a careful operator waits, so
    that nothing is lifted before the fingers have closed on it.
    """
    dt = world.timestep
    fingers = world.fingers
    k = still = 0  # still: physics steps since the fingers last moved

    def step(q) -> None:
        nonlocal still
        world.set_arm_target(q if offsets is None else q + offsets[k])
        if fingers is not None:
            fingers.update(dt)
        world.step()
        if fingers is not None:
            still = 0 if fingers.ramping or fingers.moving() else still + 1
        if observer is not None:
            observer(world, seg.label, *(() if offsets is None else (q,)))

    for seg in motion.segments:
        if fingers is None:
            world.set_gripper(seg.gripper)
        elif seg.gripper != fingers.target:
            fingers.command(seg.gripper)
        for q in seg.targets(dt):
            step(q)
            k += 1
        if fingers is not None and np.all(seg.q == seg.q[0]):
            k_last, k = k, max(k - 1, 0)  # the hold's last offset goes on
            for _ in range(int(round(FINGERS_MOST_S / dt))):
                if still * dt >= FINGERS_STILL_S:
                    break
                step(seg.q[-1])
            k = k_last
