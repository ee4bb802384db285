"""Back to where the command started, before a skill whose data starts there: the phases' retreat.

Why: drawer_put's middle phase, run as drawer_stow's skill (runtime/phases.py, policy.phased.SKILL_PHASE), was
taught on episodes that start with the arm at its start pose and the drawer open; inside drawer_put it would start
at the handle the opening just let go, where the images look like the start of the closing cycle and the policy
went back to the handle in a third of its failures (policy/EXPERIMENTS.md, "drawer_put's middle cycle under a text
of its own"). So before that phase the arm goes back to the pose the command started from: straight up to that
pose's height first (off the handle, never sideways through the cabinet), then across to it, turning on the way.
The chunks go to the controller like the policy's, through the same safety filter; the skill takes over once the
arm is there, or after `max_seconds` wherever it got to (a retreat held up by the safety layer must not eat the
episode's time).

The retreat starts only once the hand is empty. A grasp cycle ends when the command drops below closing
(policy.stage), and a hand told to open is still round the handle for a few tenths of a second. Fingers that
nothing stops reach their request, so `free_fingers` asks that the 2F-85's measured position be at its request,
and the retreat waits `settle` seconds more, as the collector holds still after a release (datagen.primitives'
RELEASE_SECONDS); a hand still holding after `wait_seconds` leaves the skill to go on from where it is. While it
waits, the arm holds where it is with the hand told to open fully (`hold_chunk`), rather than the next skill
moving an arm whose fingers are still round the handle (policy/EXPERIMENTS.md, "drawer_put's phase switches").
(A retreat before "close the drawer" was measured and not kept: from home the closing skill saw the object in
the drawer, which drawer_close's data never shows; policy/EXPERIMENTS.md, "Back to the start before closing".)

numpy only, like the bundle's inference path: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.action_frame import rot6d_of, rotations
from sim.rotations import matrix_to_rotvec, rotvec_to_matrix


@dataclass(frozen=True)
class Retreat:
    speed: float = 0.15  # m/s along the path: well inside the safety layer's 0.25 m/s collaborative speed
    turn: float = 0.6  # rad/s
    reach: float = 0.01  # m: there, when this close ...
    reach_angle: float = 0.05  # rad: ... and turned this close
    max_seconds: float = 8.0
    wait_seconds: float = 2.0  # for the hand to be empty after the phase begins; else no retreat
    at_request: float = 0.03  # fingers this close to their position request: nothing holds them, nor they it
    settle: float = 0.4  # s with free fingers before moving


def angle_between(R0: np.ndarray, R1: np.ndarray) -> float:
    """The rotation angle [rad] from R0 to R1."""
    return float(np.linalg.norm(matrix_to_rotvec(R0.T @ R1)))


def _turned(R0: np.ndarray, R1: np.ndarray, f: float) -> np.ndarray:
    """R0 turned the fraction f of the way to R1 about their common axis (a slerp)."""
    return R0 @ rotvec_to_matrix(f * matrix_to_rotvec(R0.T @ R1))


def retreat_chunk(pose: np.ndarray, start: np.ndarray, gripper: float, n: int, dt: float,
                  cfg: Retreat = Retreat()) -> np.ndarray:
    """(n, 10) absolute actions (position, rot6d, gripper) from the TCP `pose` (9,) toward `start` (9,), one every
    `dt` seconds: up to the start's height, then straight to it, at cfg.speed and cfg.turn; the gripper held."""
    p0, p1 = np.asarray(pose[:3], np.float64), np.asarray(start[:3], np.float64)
    lift = np.array([p0[0], p0[1], max(p0[2], p1[2])])
    legs = [np.linalg.norm(lift - p0), np.linalg.norm(p1 - lift)]
    R0, R1 = rotations(np.asarray(pose[3:9])), rotations(np.asarray(start[3:9]))
    angle = angle_between(R0, R1)
    out = np.empty((n, 10), np.float32)
    for k in range(n):
        s = (k + 1) * dt * cfg.speed  # arc length travelled by this action
        if s <= legs[0]:
            p = p0 + (lift - p0) * (s / legs[0])
        else:
            p = lift + (p1 - lift) * min(1.0, (s - legs[0]) / legs[1]) if legs[1] > 0 else lift
        f = 1.0 if angle < 1e-9 else min(1.0, (k + 1) * dt * cfg.turn / angle)
        out[k, :3], out[k, 3:9], out[k, 9] = p, rot6d_of(_turned(R0, R1, f)), gripper
    return out


def hold_chunk(pose: np.ndarray, n: int, gripper: float = 0.0) -> np.ndarray:
    """(n, 10) absolute actions that hold the TCP `pose` (9,) with the gripper at `gripper` (0: open)."""
    out = np.empty((n, 10), np.float32)
    out[:, :9], out[:, 9] = np.asarray(pose[:9], np.float32), gripper
    return out


def arrived(pose: np.ndarray, start: np.ndarray, cfg: Retreat = Retreat()) -> bool:
    """Whether the TCP `pose` (9,) is at `start` (9,) within cfg.reach and cfg.reach_angle."""
    near = np.linalg.norm(np.asarray(pose[:3], np.float64) - np.asarray(start[:3], np.float64)) <= cfg.reach
    return bool(near and angle_between(rotations(np.asarray(pose[3:9])), rotations(np.asarray(start[3:9])))
                <= cfg.reach_angle)


def free_fingers(command: float, closure: float, cfg: Retreat = Retreat()) -> bool:
    """Whether the fingers are where they were asked to go (0 open .. 1 closed): nothing in their way."""
    return abs(float(closure) - float(command)) <= cfg.at_request
