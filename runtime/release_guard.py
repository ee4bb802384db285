"""The release guard: while the fingers hold the object of the object query's grasp cycle, the policy's opening is
held back where the arm is far from the drop point that query gives and high above where the object lay, so that the
object is not let go in the air on its way.

Why: the denoiser decides to let go by the height and the look of the scene as much as by where the drop is, and now
and then it opens over the wrong place: drawer_stow seed 100602 lifted the block 13 cm above where it lay and let it
go right there, 24 cm from the drawer; it fell back onto the table and the arm went on to the drawer empty. Of step
37's 200 drawer_stow episodes, 9 let their object go in the air more than 10 cm from the drawer (policy/EXPERIMENTS.md,
"The release guard"). A put-down is left alone: the policy sets a poorly held object back on the table to take it
again (12 of those 200 episodes do, and complete), and such an opening comes with the hand low, at the object's
resting height.

How: in the object query's grasp cycle, with its points known, while the fingers are commanded closed and measure
more than HELD_GAP short of the request (something stops them), each action of the chunk that asks them open (below
policy.stage.CLOSED) at a point more than FAR_M from the drop horizontally and more than LOW_M above the object's
located centre gets the standing request instead. Every action still goes through the safety layer.

And a held chunk is carried towards the drop: each action moved horizontally towards it by at most CARRY_M_S times
its time into the chunk, and raised to the drop's height where it is lower. Why: the policy that wants to let go
where it is mostly stays there, asking again at every tick; seed 100602 on an AVX-512 machine hovered 12-18 cm from
the drop with the block held for 23 s, every opening held, until the episode ran out (policy/EXPERIMENTS.md, "The
release guard carries the held object towards the drop"). Once it has carried, the guard holds openings until the
hand is within NEAR_M of the drop, not FAR_M: carried to 10 cm it would let go over the drawer's wall.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import CLOSED, GRIPPER_COLUMN

FAR_M = 0.10  # horizontally from the drop: the drawer's cavity is about 14 cm across, the locator 2 cm off (median)
LOW_M = 0.04  # above the object's resting centre: lower than this the hand is putting the object down, not dropping it
CARRY_M_S = 0.10  # how fast a held chunk is moved towards the drop: 15 cm in 1.5 s, replanned at every tick on the way
NEAR_M = 0.03  # once carried: how near the drop an opening is let through
# The fingers are stopped by something when they measure this much more open than requested. Not "less closed than
# an empty close" (0.9): a policy that hovers its request at 0.77-0.87 after the object slipped out has its fingers
# there too, and they were taken for a hold (drawer_stow seed 100610: the empty hand carried to the drawer). A held
# block measures 0.17-0.55 closed under a full request.
HELD_GAP = 0.15


class ReleaseGuard:
    """One command's release guard (module doc); inactive where `enabled` is False."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.held = 0  # chunks whose opening was held back (and carried towards the drop)

    def chunk(self, actions: np.ndarray, objects, stage: int, command: float, closure: float,
              dt: float) -> np.ndarray:
        """The chunk (n, 10; base frame; one action every `dt` s) with its openings far from the drop held back and
        carried towards it, or as it was (module doc). `objects` is the command's policy.object_query.ObjectQuery;
        `command` and `closure` the gripper's standing position request and measured closure (0 open .. 1 closed);
        `stage` the grasp cycles completed."""
        if not (self.enabled and objects.active and stage == objects.stage and objects.points is not None
                and command >= CLOSED and command - closure > HELD_GAP):
            return actions
        drop, rest_z = np.asarray(objects.drop, np.float64), float(objects.points[0][2])
        pos = np.asarray(actions[:, :3], np.float64)
        gap = drop[:2] - pos[:, :2]
        far = np.hypot(gap[:, 0], gap[:, 1])
        held = ((np.asarray(actions[:, GRIPPER_COLUMN]) < CLOSED) & (pos[:, 2] > rest_z + LOW_M)
                & (far > (NEAR_M if self.held else FAR_M)))
        if not held.any():
            return actions
        out = np.array(actions, copy=True)
        out[held, GRIPPER_COLUMN] = command
        reach = CARRY_M_S * dt * (1 + np.arange(len(out)))  # how far each action may be moved by its time
        step = gap * (np.minimum(far, reach) / np.maximum(far, 1e-9))[:, None]
        out[:, :2] += step.astype(out.dtype)
        out[:, 2] = np.maximum(out[:, 2], drop[2]).astype(out.dtype)
        self.held += 1
        return out


__all__ = ["ReleaseGuard"]
