"""The chunk's gripper channel -> open/close commands, with hysteresis, through the safety gripper limits.

Why a binary decision: the policy regresses a 0..1 closure that the data recorded as open/close commands;
forwarding every small change would restart the 2F-85's move (and its object detection) at 10 Hz. A band
(`gripper_open_below` .. `gripper_close_above`) turns it into edges; only an edge sends a command, and only
while the stop state allows motion (an e-stop or protective stop must not drop a held object).

Units: the driver speaks normalised registers (position 0 open .. 1 closed, speed/force 0..1); safety's
`limit_gripper` speaks metres, m/s and N. The 2F-85's ranges convert between them.
"""

from __future__ import annotations

from safety.gripper import limit_gripper

STROKE_M = 0.085  # 2F-85 finger gap fully open
SPEED_RANGE = (0.020, 0.150)  # m/s at normalised speed 0 and 1
FORCE_RANGE = (20.0, 235.0)  # N at normalised force 0 and 1


def _norm(x: float, lo: float, hi: float) -> float:
    return min(1.0, max(0.0, (x - lo) / (hi - lo)))


class GripperChannel:
    def __init__(self, gripper, limits, config):
        self.gripper, self.limits, self.cfg = gripper, limits, config
        self.closed: bool | None = None  # the commanded state; None until the first command
        self.commands = 0
        self._edge_at = -float("inf")  # when the last command was sent

    def update(self, value: float | None, now: float, allowed: bool, events) -> bool | None:
        """Feed the channel's value at this cycle; returns True/False (closed/open) when a command was sent."""
        if self.gripper is None or value is None or not allowed:
            return None
        cfg = self.cfg
        want = self.closed
        if value >= cfg.gripper_close_above:
            want = True
        elif value <= cfg.gripper_open_below:
            want = False
        if want is None or want == self.closed:
            return None
        if self.closed is not None and now - self._edge_at < cfg.gripper_min_hold:
            return None
        opening = 0.0 if want else STROKE_M
        cmd, _ = limit_gripper(self.limits, opening, cfg.gripper_speed, cfg.gripper_force, now, events)
        if cmd is None:
            return None
        position = 1.0 - min(1.0, cmd.opening / STROKE_M)
        ok = self.gripper.move(position, _norm(cmd.speed, *SPEED_RANGE), _norm(cmd.force, *FORCE_RANGE), wait=False)
        if ok:
            if self.closed is not None:  # the first command only sets the state: no hold after it
                self._edge_at = now
            self.closed = want
            self.commands += 1
            return want
        return None


__all__ = ["GripperChannel"]
