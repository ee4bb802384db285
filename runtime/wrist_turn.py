"""The wrist turn the turn query asks for (policy/turn_query.py), held on the policy's actions until its first
grasp cycle ends.

Why: the policy does not turn the wrist for a block's yaw (its features do not say it), so it closes a uniform
0-45 degrees off the block's faces, and off-face closes are where its stacks fail. The turn locator says the turn
on the way to the grasp; this sets the yaw of every action of the chunk to the target yaw, reached at `rate` from
the wrist's yaw now, about the vertical, so the policy's position, tilt and gripper are left as they were. After
the first grasp cycle (a let-go, or a close on nothing) the policy's own yaw is sent again: its training episodes
turn the wrist back only through what the collector did, and a retry's object may lie elsewhere.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.action_frame import rot6d_of, rotations
from policy.grasp_axis import yaw_of
from sim.rotations import rotvec_to_matrix, wrap_angle

DEFAULT_RATE = 0.6  # rad/s: the look's and the retreats' turning speed (runtime.retreat.Retreat.turn)


def hold_yaw(actions: np.ndarray, pose: np.ndarray, target: float, dt: float,
             rate: float = DEFAULT_RATE) -> np.ndarray:
    """(n, 10) actions (position, rot6d, gripper) one every `dt` s, each rot6d turned about the vertical so its
    yaw is `target` [rad], approached from `pose`'s (9,: the TCP now) at no more than `rate` rad/s."""
    out = np.array(actions, np.float32, copy=True)
    now = float(yaw_of(pose[3:9]))
    gap = float(wrap_angle(target - now))
    for k in range(len(out)):
        limit = rate * (k + 1) * dt
        want = now + float(np.clip(gap, -limit, limit))
        R = rotations(np.asarray(out[k, 3:9], np.float64))
        out[k, 3:9] = rot6d_of(rotvec_to_matrix([0.0, 0.0, wrap_angle(want - yaw_of(out[k, 3:9]))]) @ R)
    return out


def steer(turn, actions: np.ndarray, images: dict, proprio: np.ndarray, stage: int, closing: bool,
          dt: float) -> np.ndarray:
    """The policy's chunk with the turn query's yaw held (module doc), as `sudd eval` and the policy node both play
    it: `turn` (policy.turn_query.TurnQuery) asked about these frames while the fingers have not yet closed
    (`closing` False), its target held while no grasp cycle has ended (`stage` 0); else the chunk as it was."""
    if not turn.active or stage != 0:
        return actions
    if not closing:
        turn.ask(images, proprio)
    return actions if turn.target is None else hold_yaw(actions, proprio[-1], turn.target, dt)
