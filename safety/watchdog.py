"""Stale-command watchdog: is the newest command fresh enough to follow?

Each cycle the filter passes the clock `now` and the time the command was made (`command_time`, same clock).
A command is followed only when it is *fresh*: not older than `max_age`, not ahead of the clock by more than
`max_future`, and not older than a command already used (commands may repeat their timestamp, e.g. one
policy chunk sampled over many cycles). Anything else makes the filter stop smoothly and hold; it resumes
on the next fresh command, never on a late one.
"""

from __future__ import annotations

import math

FRESH, STALE, OUT_OF_ORDER, FUTURE, INVALID = "fresh", "stale", "out_of_order", "future", "invalid"


class CommandWatchdog:
    def __init__(self, max_age: float = 0.1, max_future: float = 0.05):
        if not (max_age > 0.0 and max_future >= 0.0):
            raise ValueError(f"max_age must be > 0 and max_future >= 0, got {max_age}, {max_future}")
        self.max_age = float(max_age)
        self.max_future = float(max_future)
        self.last_time = -math.inf  # newest command_time followed so far
        self.stale_since: float | None = None

    def check(self, now: float, command_time: float) -> str:
        try:
            now, command_time = float(now), float(command_time)
        except (TypeError, ValueError):
            return INVALID
        if not (math.isfinite(now) and math.isfinite(command_time)):
            return INVALID
        if command_time < self.last_time:
            return OUT_OF_ORDER
        age = now - command_time
        if age > self.max_age:
            if self.stale_since is None:
                self.stale_since = now
            return STALE
        if age < -self.max_future:
            return FUTURE
        self.last_time = command_time
        self.stale_since = None
        return FRESH

    def age(self, now: float) -> float:
        return now - self.last_time


__all__ = ["CommandWatchdog", "FRESH", "STALE", "OUT_OF_ORDER", "FUTURE", "INVALID"]
