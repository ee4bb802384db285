"""The chunk's gripper channel -> finger commands at a few levels, with hysteresis, through the safety gripper
limits.

Why levels and not the regressed value: the policy regresses a 0..1 closure that the data recorded as a few
commands (open and closed; the drawer families also a half-open pre-shape that reaches between a handle and
the drawer front); forwarding every small change would restart the 2F-85's move (and its object detection) at
10 Hz. The channel snaps to the nearest of `gripper_levels` with a band between each two neighbours
(`gripper_open_below` .. `gripper_close_above` of their gap), so only a change of level sends a command, and
only while the stop state allows motion (an e-stop or protective stop must not drop a held object). The top
level is a grasp (closed with the configured force, checked for an empty close); the others are positions.

An empty close is undone (`reopen_empty_grasp`): when the gripper reports its fingers stopped at the closed
end with nothing between them (the 2F-85's object detection, OBJ = 3), the fingers open and the policy's close
is ignored for `reopen_hold` or until its channel reads open. Why: a policy distilled from grasps that worked
has never seen an empty closed gripper; it carries one on to the bin and the episode is lost, where open
fingers above the object are an approach it knows. The gripper is asked only every `CHECK_PERIOD_S` while
a close stands unverified (the real driver's status is a socket round trip, too slow for every cycle).

The channel also keeps the least closure the fingers can have until its next command (`closure_bound`), which
the safety filter places its finger points for (safety.filter.set_finger_closure): a half-open pre-shape then
reaches under a cabinet's top to its handle, where the points of open fingers would reach into the top's
keep-out box. An opening command takes the bound down at once, and is held while the fingers' points at the
new opening would reach into a keep-out box where the arm is (`may_open`, the filter's check). Held back so, the
fingers open as far as the box allows where that lets go of what they hold (at least `LET_GO` more open than the
bound), and the rest of the way once the arm has moved clear. Why: an object about as wide as the half-open level
stays in fingers held there, and inside a drawer, where open fingers would reach into its walls' boxes, the policy
asked them open for 30 s with the object still in the hand (drawer_put seed 100527, drawer_stow 100532;
policy/EXPERIMENTS.md, "A pause already held"). A closing
command raises it only as the gripper reports its fingers closed (asked every `CHECK_PERIOD_S` from
`SETTLE_S` after the command until they stop): fingers that close on an object stop at its width.

Units: the driver speaks normalised registers (position 0 open .. 1 closed, speed/force 0..1); safety's
`limit_gripper` speaks metres, m/s and N. The 2F-85's ranges convert between them (sim/finger_drive.py).
"""

from __future__ import annotations

import math

from safety.gripper import limit_gripper
from sim.finger_drive import force_register, speed_register

STROKE_M = 0.085  # 2F-85 finger gap fully open
CHECK_PERIOD_S = 0.1  # how often an unverified close asks the gripper what it holds
SETTLE_S = 0.2  # after a close edge, the fingers have not started to move yet: no verdict before this
EMPTY_CLOSED = 0.9  # finger closure (0 open .. 1 closed) beyond which a stopped gripper holds nothing
PARTIAL_STEP = 0.05  # the closures tried for an opening a keep-out box holds back, most open first
LET_GO = 0.1  # a partial opening at least this much more open than the bound lets go of what the fingers hold


BINARY = (0.0, 1.0)  # open and closed: the levels of a bundle that records none


class GripperChannel:
    def __init__(self, gripper, limits, config, may_open=None):
        """`may_open(closure)`: whether the fingers may open to that closure now (None: always)."""
        self.gripper, self.limits, self.cfg = gripper, limits, config
        self.may_open = may_open
        self.closure_bound = 0.0  # the least closure the fingers can have until the next command (0: open)
        self._closing_to: float | None = None  # the closure of a close whose fingers are still moving
        self._next_bound_check = 0.0
        self._state_cache: tuple | None = None  # (cycle time, GripperState)
        self.levels = tuple(config.gripper_levels or BINARY)
        self.level: int | None = None  # index of the commanded level; None until the first command
        self.commands = 0
        self.empty_closes = 0  # closes undone because the fingers caught nothing
        self._edge_at = -float("inf")  # when the last command was sent
        self._verified = False  # the standing close holds an object (no need to ask again)
        self._next_check = 0.0
        self._reopened_until: float | None = None  # the policy's close is ignored until then
        self._short_of: tuple | None = None  # (closure, command) of an opening sent only in part: the rest wanted

    def update(self, value: float | None, now: float, allowed: bool, events) -> bool | None:
        """Feed the channel's value at this cycle; returns True/False (closed/open) when a command was sent."""
        if self.gripper is None:
            return None
        self._track_closure(now)
        if value is None or not allowed:
            return None
        cfg = self.cfg
        if self._reopened_until is not None:
            if value <= self._band(len(self.levels) - 2)[0] or now >= self._reopened_until:
                self._reopened_until = None  # the policy agrees, or has had its time to approach again
            else:
                value = 0.0
        elif self.closed and cfg.reopen_empty_grasp and self._caught_nothing(now):
            self.empty_closes += 1
            self._reopened_until = now + cfg.reopen_hold
            value = 0.0
            if events is not None:
                events.report("gripper_empty_grasp", now, message="the fingers closed on nothing: reopened, "
                              f"the policy's close ignored for up to {cfg.reopen_hold:g} s")
        want = self._level_for(value)
        if want is not None and want == self.level and self._short_of is not None:
            return self._open_the_rest()
        if want is None or want == self.level:
            return None
        if self.level is not None and now - self._edge_at < cfg.gripper_min_hold:
            return None
        opening = STROKE_M * (1.0 - self.levels[want])
        cmd, _ = limit_gripper(self.limits, opening, cfg.gripper_speed, cfg.gripper_force, now, events)
        if cmd is None:
            return None
        position = 1.0 - min(1.0, cmd.opening / STROKE_M)
        short_of = None
        if position < self.closure_bound and self.may_open is not None and not self.may_open(position):
            part = self._widest_allowed(position)
            if part is None:
                if events is not None:
                    events.report("gripper_open_held", now, value=position, limit=self.closure_bound,
                                  message="the fingers would open into a keep-out box here: held until the arm "
                                          "moves clear (closure wanted / now)")
                return None
            if events is not None:
                events.report("gripper_open_partial", now, value=part, limit=position,
                              message="the fingers opened only as far as the keep-out boxes allow here, the rest "
                                      "once the arm moves clear (closure now / wanted)")
            short_of, position = (position, cmd), part
        ok = self.gripper.move(position, speed_register(cmd.speed), force_register(cmd.force), wait=False)
        if ok:
            if self.level is not None:  # the first command only sets the state: no hold after it
                self._edge_at = now
            self.level = want
            self.commands += 1
            self._short_of = short_of
            self._verified = False
            self._next_check = now + SETTLE_S  # no verdict before the fingers move
            if position <= self.closure_bound:
                self.closure_bound, self._closing_to = position, None
            else:  # the bound rises as the gripper reports the fingers closing, read with the verdict's state
                self._closing_to = position
                self._next_bound_check = self._next_check
            return self.closed
        return None

    def _widest_allowed(self, position: float) -> float | None:
        """The most open closure short of `position` the keep-out boxes allow here, where it lets go of what the
        fingers hold (LET_GO more open than the bound); None where none does."""
        c = position + PARTIAL_STEP
        while c <= self.closure_bound - LET_GO + 1e-9:
            if self.may_open(c):
                return c
            c += PARTIAL_STEP
        return None

    def _open_the_rest(self) -> bool | None:
        """The rest of an opening sent only in part, once the keep-out boxes allow it."""
        position, cmd = self._short_of
        if not self.may_open(position):
            return None
        if not self.gripper.move(position, speed_register(cmd.speed), force_register(cmd.force),
                                 wait=False):
            return None
        self._short_of = None
        self.closure_bound = min(self.closure_bound, position)
        self.commands += 1
        return self.closed

    def _track_closure(self, now: float) -> None:
        """Raise the closure bound as a close's fingers are reported closing: from a report taken after the
        command reached the gripper, they only close further (to the command, or until they meet an object)."""
        if self._closing_to is None or now < self._next_bound_check:
            return
        self._next_bound_check = now + CHECK_PERIOD_S
        s = self._state(now)
        measured = float(s.position) if math.isfinite(s.position) else 0.0
        self.closure_bound = max(self.closure_bound, min(measured, self._closing_to))
        if not s.is_moving or measured >= self._closing_to:
            self._closing_to = None

    def _state(self, now: float):
        """The gripper's state, asked at most once per cycle (the bound and the empty-close check share it)."""
        if self._state_cache is None or self._state_cache[0] != now:
            self._state_cache = (now, self.gripper.state())
        return self._state_cache[1]

    @property
    def closed(self) -> bool | None:
        """Whether the commanded level is the grasp (the top one); None before the first command."""
        return None if self.level is None else self.level == len(self.levels) - 1

    def _band(self, i: int) -> tuple[float, float]:
        """The hysteresis band between level i and level i + 1: below it reads i, above it i + 1."""
        lo, hi = self.levels[i], self.levels[i + 1]
        return lo + self.cfg.gripper_open_below * (hi - lo), lo + self.cfg.gripper_close_above * (hi - lo)

    def _level_for(self, value: float) -> int | None:
        """The level `value` asks for; inside a band, the standing level when it is one of the band's two,
        else the one of them nearer to it (None before the first command: no level asked for yet, and for a
        value that is not a number)."""
        if not math.isfinite(value):
            return None
        for i in range(len(self.levels) - 1):
            below, above = self._band(i)
            if value <= below:
                return i
            if value < above:
                if self.level is None:
                    return None
                return self.level if self.level in (i, i + 1) else (i if self.level < i else i + 1)
        return len(self.levels) - 1

    def _caught_nothing(self, now: float) -> bool:
        """Whether the standing close has stopped with nothing between the fingers (asks the gripper at most
        every CHECK_PERIOD_S, and not again once it reports an object: a slip later on is not caught)."""
        if self._verified or now < self._next_check:
            return False
        self._next_check = now + CHECK_PERIOD_S
        s = self._state(now)
        self._verified = s.object_detected
        return not s.object_detected and not s.is_moving and s.position >= EMPTY_CLOSED


__all__ = ["GripperChannel"]
