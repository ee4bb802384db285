"""How fast the arm follows the policy: its chunks' actions spaced 1 / (control_hz x speed) apart.

Why: the collector comes in at 5 cm/s for its last second before a grasp; the distilled policy, replanning
every 0.1 s, reaches the drawer front at 10-25 cm/s with its finger links, and the contact force stops the arm
(8 of 20 drawer_close episodes of the shipped bundle). Played at half the recorded pace (speed 0.5: actions
0.2 s apart, a chunk every 0.2 s), the same bundle completes drawer_close 20/20 with no stop, within the same
time limit (policy/EXPERIMENTS.md, "Half speed"). Only the execution slows: the observation history stays
1 / control_hz apart, the spacing the policy was trained on, so it sees the motions it knows, slower.
"""

from __future__ import annotations

import math

MIN_SPEED = 0.1


def check_speed(speed: float) -> float:
    """The speed as a float in [MIN_SPEED, 1], or a ValueError that says what to give."""
    s = float(speed)
    if not (math.isfinite(s) and MIN_SPEED <= s <= 1.0):
        raise ValueError(f"speed {speed!r}: expected a fraction of the demonstrated pace in [{MIN_SPEED}, 1] "
                         "(1: as recorded; 0.5: half as fast, actions 2 / control_hz apart)")
    return s


def action_period_ns(control_hz: float, speed: float) -> int:
    """Nanoseconds between a chunk's actions (and between the policy's ticks) at `speed`."""
    return int(round(1e9 / (control_hz * check_speed(speed))))
