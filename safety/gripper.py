"""Gripper command limits: opening, speed and force clamped into the configured 2F-85 limits."""

from __future__ import annotations

import math
from typing import NamedTuple


class GripperCommand(NamedTuple):
    opening: float  # m between the fingers (0 closed)
    speed: float  # m/s
    force: float  # N


def limit_gripper(limits, opening: float, speed: float, force: float, now: float = 0.0, events=None):
    """Clamp a gripper command into [0, limit] per value.

    A non-finite speed or force becomes 0 (the gripper does not move / does not squeeze); a non-finite
    opening cannot be made safe, so the command is dropped (None: send nothing, the gripper keeps still).
    Returns (GripperCommand or None, [(field, requested, limit), ...]) and reports each change as a
    "gripper_<field>" event when `events` (an EventCoalescer) is given.
    """
    g = limits.gripper
    changed = []
    vals = []
    for name, x, hi, safe in (("opening", opening, g.max_opening, None), ("speed", speed, g.max_speed, 0.0),
                              ("force", force, g.max_force, 0.0)):
        try:
            x = float(x)
        except (TypeError, ValueError):
            x = math.nan
        if not math.isfinite(x):
            changed.append((name, x, hi))
            if safe is None:
                vals = None
                break
            x = safe
        elif x < 0.0 or x > hi:
            changed.append((name, x, hi))
            x = min(max(x, 0.0), hi)
        vals.append(x)
    if events is not None:
        for name, x, hi in changed:
            events.report("gripper_" + name, now, value=x if math.isfinite(x) else None, limit=hi)
    return (GripperCommand(*vals) if vals is not None else None), changed


__all__ = ["GripperCommand", "limit_gripper"]
