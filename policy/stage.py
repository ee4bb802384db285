"""Grasp cycles so far: which grasp of a multi-grasp task comes next, read from the gripper's own history.

Why: drawer_put grasps three times (the handle, the object, the handle again). Two observation steps (0.2 s)
do not say which grasp comes next, and the policy's view of the scene did not either: after the drawer is open
its head pointed at the handle again (policy/EXPERIMENTS.md, "drawer_put: the head points at the handle").
How many times the gripper has closed on something and let it go since the command started is measured
alike on the real gripper and in sim, and costs no perception.

A cycle is a hold followed by a release: the gripper is commanded closed (target >= CLOSED), the fingers stop short
of closing fully (measured closure < AIR: they were stopped by something; closing on nothing reaches ~1 and is a
missed grasp, which the collector retries without moving on), and the command opens again (the collector's half-open
pre-shape for the handle, 0.5, is not a close) below RELEASED, and the fingers then measure at least OPENED more
open than the most they held, or close again on nothing. Why the fingers too: the gripper channel
(runtime.controller.gripper) passes through the 0.5 level on its way down, and an object about as wide as that level
is still held there; counted as let go, drawer_stow's policy lost the place point given in that cycle, closed again
on the object it still held and carried it onto the drawer's front wall (4 of step 34's 11 drawer_stow failures on
seeds 100500-100539; policy/EXPERIMENTS.md, "Let go means the fingers opened"). The band between RELEASED and CLOSED
changes nothing: a policy's gripper channel is continuous, and one that lets go slowly hovers at CLOSED for a tick
or two (0.75, 0.75, 0.66 in successive chunks), which without the band counted two cycles for one release and sent
drawer_put to its closing phase with nothing stowed (3 of 40 fresh episodes of step 29; policy/EXPERIMENTS.md,
"drawer_put's phase switches"). The collector's commands cross the band once, so its counts are the same with or
without it. On the 391 verified collector drawer_put episodes of out/data_ft: 0 cycles while opening the drawer, 1
while taking the object to it, 2 while closing it, in 338 (86 %); the rest also count a re-grasp of a slipping
handle or object. Both inputs are what a 2F-85 reports (its position request and position), in sim and on the robot.
The count at an observation is the cycles completed up to and including its newest step; the policy reads it as a
one-hot of `bins` classes, the last one meaning "bins - 1 or more".

Torch-free (numpy only): the runtime's policy node and the evaluation count the same way as the training data.
"""

from __future__ import annotations

import numpy as np

CLOSED = 0.75  # gripper command at or above this: closing (the collector's levels: 0 open, 0.5 pre-shape, 1 closed)
RELEASED = 0.6  # and below this, after a close: let go (above the 0.5 pre-shape; the hysteresis band's bottom)
OPENED = 0.05  # and the fingers measured this much more open than they held (0.03 took a slip at 0.5 for a let-go)
AIR = 0.97     # measured closure at or above this: closed on nothing (the 2F-85's fully closed fingers)
GRIPPER_COLUMN = 9  # datagen.schema: the gripper's column in proprio (measured closure) and action (command)


class GraspCycles:
    """Counts completed hold-and-release cycles from (command, closure) pairs fed one at a time, oldest first."""

    def __init__(self) -> None:
        self.count = 0
        self._closing = False  # commanded closed since the last release
        self._peak = 0.0       # the most closed the fingers got meanwhile
        self._letting_go = False  # asked open after a hold, the fingers not yet measured open

    def update(self, command: float, closure: float) -> int:
        """Feed the gripper's position request and measured closure (both 0 open .. 1 closed) at one step;
        returns the cycles completed so far."""
        cmd, c = float(command), float(closure)
        if not (np.isfinite(cmd) and np.isfinite(c)):
            raise ValueError(f"gripper command and closure must be finite numbers in [0, 1], got {command!r}, "
                             f"{closure!r}")
        if cmd >= CLOSED:
            if self._letting_go and c >= AIR:  # closed again on nothing: what it held was let go meanwhile
                self.count += 1
                self._letting_go, self._peak = False, 0.0
            self._closing = True
            self._peak = max(self._peak, c)
        elif self._closing and cmd < RELEASED:
            if self._peak >= AIR or c <= self._peak - OPENED:
                self.count += self._peak < AIR
                self._closing, self._peak, self._letting_go = False, 0.0, False
            else:
                self._letting_go = True  # asked open, the fingers still where they held
        return self.count

    def reset(self) -> None:
        self.__init__()


def cycles_per_step(command: np.ndarray, closure: np.ndarray) -> np.ndarray:
    """(T,) gripper commands in effect and (T,) measured closures of one episode -> (T,) int64 cycles
    completed up to each step."""
    counter = GraspCycles()
    return np.asarray([counter.update(a, c) for a, c in zip(np.asarray(command, np.float64),
                                                           np.asarray(closure, np.float64))], np.int64)


def commands_in_effect(action: np.ndarray) -> np.ndarray:
    """A recorded episode's (T, Da) actions -> (T,) the gripper command in effect at each step: the recorded
    action at step t is the target of step t + 1 (datagen.recorder), so step t runs action t - 1's; the first
    step runs its own."""
    g = np.asarray(action)[:, GRIPPER_COLUMN]
    return np.concatenate([g[:1], g[:-1]])


def one_hot(count: int, bins: int) -> np.ndarray:
    """(bins,) float32: the class of `count` cycles (the last class holds bins - 1 and more)."""
    if bins < 1:
        raise ValueError(f"stage bins must be >= 1, got {bins}")
    if count < 0:
        raise ValueError(f"grasp cycles must be >= 0, got {count}")
    out = np.zeros(bins, np.float32)
    out[min(int(count), bins - 1)] = 1.0
    return out


def with_stage(proprio: np.ndarray, count: int, bins: int) -> np.ndarray:
    """Normalized proprio (..., To, Dp) -> (..., To, Dp + bins): every step gets the newest step's stage, as
    the policy reads it (`stage_bins` 0: unchanged)."""
    p = np.asarray(proprio, np.float32)
    if bins == 0:
        return p
    stage = np.broadcast_to(one_hot(count, bins), p.shape[:-1] + (bins,))
    return np.concatenate([p, stage], axis=-1)
