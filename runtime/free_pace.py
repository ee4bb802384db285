"""Free-space pace: a family slowed for its contacts plays at the recorded speed while the hand is high above
everything in the cell.

Why: the drawers play at half the recorded speed (the manifest's `pace`) because their force stops are a matter
of speed at the handle and the cabinet's front (policy/EXPERIMENTS.md, "The pace per task family"). But half of a
drawer skill's time is spent well above the cabinet, where the hand can touch nothing. Played at speed 1 there, step
37's drawer skills are 2-6 s quicker at no cost in success: drawer_put 141/160 either way, its median success
39.8 s instead of 45.6; drawer_open 58/60 (56 before) in 10.4 s instead of 12.6; drawer_close 59/60 (58) in 9.3 s
instead of 12.4 (policy/EXPERIMENTS.md, "Free-space pace"). A human integrator programs an arm the same way: fast
in free space, slow on the final approach.

How: the ceiling is the highest thing the cell declares (the table plane, the top of every keep-out box of the
safety limits). While the TCP is more than CLEAR_M above it, the chunks play at speed 1; once it comes down below
CLEAR_M - BAND_M, at the family's own pace again. The band keeps a hand hovering at the line from switching at
every tick. A family already at speed 1 is untouched. The line is only as good as the cell the limits declare: a
real cell without a limits file gets no ceiling, and every family keeps its pace there.

Plain Python, no imports: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

CLEAR_M = 0.06  # above the ceiling: the 2F-85's pads reach 1.8 cm past the TCP (safety.limits), so 4 cm to spare
BAND_M = 0.02  # hysteresis: back to the family's pace only this much lower


def ceiling_of(limits) -> float:
    """The highest fixed thing of the cell a safety.SafetyLimits declares [m, base frame]: its table plane or
    the top of its highest keep-out box."""
    ws = limits.workspace
    return max([float(ws.table_z)] + [float(box[5]) for box in ws.keepout])


class FreePace:
    """One command's free-space pace (module doc); `ceiling_z` None or `enabled` False: always the family's."""

    def __init__(self, ceiling_z: float | None, enabled: bool = True):
        self.ceiling = None if ceiling_z is None else float(ceiling_z)
        self.enabled = enabled and self.ceiling is not None
        self.free = False  # the hand above the line, playing at speed 1
        self.ticks = 0  # ticks played faster than the family's pace

    @property
    def line(self) -> float | None:
        """The TCP height [m, base frame] above which a slowed family plays at speed 1; None: never."""
        return self.ceiling + CLEAR_M if self.enabled else None

    def speed(self, family_speed: float, tcp_z: float) -> float:
        """The speed to play this tick's chunk at: `family_speed` (the family's or the phase's pace), or 1 while
        the TCP (height `tcp_z`, base frame) is in free space."""
        if not self.enabled or family_speed >= 1.0:
            self.free = False
            return family_speed
        line = self.line
        self.free = tcp_z > line if not self.free else tcp_z >= line - BAND_M
        self.ticks += self.free
        return 1.0 if self.free else family_speed


__all__ = ["FreePace", "ceiling_of", "CLEAR_M", "BAND_M"]
