"""Safety events: every intervention of the filter, coalesced so a limit held for 3 s is one event, not 1500.

An intervention (a kind, optionally one joint) opens an event the first cycle it is active; the event is
emitted then, with `end=None`, so the runtime can show it at once. It stays open while the intervention recurs
within `gap` seconds, keeping the worst value seen and the count of active cycles; when it has been absent
for `gap` it is closed and emitted again with its end time (duration = end - start). So one episode of
intervention gives two emissions: the opening and the closed summary, which is the one to record.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace

INFO, WARNING, ERROR, CRITICAL = "info", "warning", "error", "critical"
SEVERITIES = (INFO, WARNING, ERROR, CRITICAL)

# What each kind means; `value` and `limit` are in the unit given.
KINDS = {
    "malformed_command": (ERROR, "command rejected (NaN/Inf, wrong shape or non-unit rotation); holding"),
    "malformed_measurement": (ERROR, "measured joint state rejected (NaN/Inf or wrong shape); holding"),
    "stale_command": (WARNING, "newest command older than the maximum age (s); stopping"),
    "out_of_order_command": (WARNING, "command older than one already used (s); ignored, holding"),
    "future_command": (WARNING, "command time ahead of the clock by more than allowed (s); holding"),
    "workspace": (WARNING, "TCP target moved onto the allowed workspace (m)"),
    "unreachable": (ERROR, "target cannot be moved into the workspace; holding"),
    "ik_fallback": (WARNING, "no IK solution on the target's branch within the Newton budget; stop policy "
                             "(brake, then hold) instead (iterations spent / budget)"),
    "joint_position": (WARNING, "joint target beyond its position limit (rad)"),
    "joint_braking": (WARNING, "joint slowed to stop before its position limit (rad/s)"),
    "velocity": (INFO, "joint velocity scaled to its limit (ratio requested / allowed)"),
    "acceleration": (INFO, "joint acceleration limited (ratio requested / allowed)"),
    "jerk": (INFO, "joint jerk limited (ratio requested / allowed)"),
    "tcp_speed": (INFO, "TCP speed scaled to its cap (m/s or rad/s)"),
    "workspace_braking": (WARNING, "slowed to stop inside the workspace / above the table (m of slack)"),
    "collision": (WARNING, "slowed near a collision (m of predicted clearance)"),
    "collision_stop": (ERROR, "stopped before a collision (m of predicted clearance)"),
    "tracking_error": (ERROR, "measured joints far from the command (rad); stopping"),
    "estop": (CRITICAL, "software emergency stop latched; waiting for an operator reset"),
    "protective_stop": (ERROR, "robot protective stop; recovery sequence running"),
    "recovery": (INFO, "protective-stop recovery step"),
    "invalid_request": (WARNING, "operator/runtime request not valid in this state; ignored"),
    "gripper_opening": (WARNING, "gripper opening outside [0, max]: clamped, or dropped if not finite (m)"),
    "gripper_speed": (INFO, "gripper speed clamped to its limit (m/s)"),
    "gripper_force": (INFO, "gripper force clamped to its limit (N)"),
    "gripper_open_held": (WARNING, "gripper opening held: the fingers would open into a keep-out box here "
                                   "(closure wanted / now)"),
    "gripper_open_partial": (WARNING, "gripper opened only as far as the keep-out boxes allow here, the rest once "
                                      "the arm moves clear (closure now / wanted)"),
}


@dataclass(frozen=True)
class SafetyEvent:
    """One intervention episode. Times are in the clock passed to the filter (seconds)."""

    kind: str
    severity: str
    message: str
    start: float
    end: float | None = None  # None while the intervention is ongoing
    value: float | None = None  # the worst value requested / seen
    limit: float | None = None  # the limit it was held to
    count: int = 1  # control cycles in which it was active
    joint: int | None = None

    @property
    def ongoing(self) -> bool:
        return self.end is None

    @property
    def duration(self) -> float:
        return 0.0 if self.end is None else self.end - self.start

    def to_dict(self) -> dict:
        d = asdict(self)
        for key in ("value", "limit"):
            if d[key] is not None and not math.isfinite(d[key]):
                d[key] = str(d[key])  # JSON has no NaN/Inf
        d["duration"] = self.duration
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), allow_nan=False)

    @classmethod
    def from_dict(cls, d: dict) -> SafetyEvent:
        d = {k: v for k, v in d.items() if k != "duration"}
        for key in ("value", "limit"):
            if isinstance(d.get(key), str):
                d[key] = float(d[key])
        return cls(**d)


def _excess(value, limit) -> float:
    if value is None or limit is None:
        return 0.0
    e = abs(value - limit)
    return e if e == e else math.inf  # NaN counts as worst


class _Open:
    __slots__ = ("event", "last", "count", "value", "limit", "excess")

    def __init__(self, event: SafetyEvent, now: float):
        self.event, self.last, self.count = event, now, 1
        self.value, self.limit, self.excess = event.value, event.limit, _excess(event.value, event.limit)


class EventCoalescer:
    """Collects `report`s during a cycle; `flush(now)` returns the events to publish this cycle."""

    _EMPTY: tuple = ()

    def __init__(self, gap: float = 0.1):
        self.gap = float(gap)
        self._open: dict[tuple, _Open] = {}
        self._new: list[SafetyEvent] = []

    def report(self, kind: str, now: float, value: float | None = None, limit: float | None = None,
               joint: int | None = None, message: str | None = None, severity: str | None = None) -> None:
        key = (kind, joint)
        rec = self._open.get(key)
        if rec is not None and now - rec.last > self.gap:  # absent too long: that episode is over
            self._new.append(self._closed(self._open.pop(key)))
            rec = None
        if rec is not None:
            if rec.last != now:
                rec.count += 1
                rec.last = now
            ex = _excess(value, limit)
            if ex > rec.excess:
                rec.value, rec.limit, rec.excess = value, limit, ex
            return
        default_sev, meaning = KINDS.get(kind, (WARNING, kind))
        text = message or meaning
        if joint is not None:
            text = f"joint {joint}: {text}"
        if value is not None:
            text += f" [value {value:.6g}" + (f", limit {limit:.6g}]" if limit is not None else "]")
        event = SafetyEvent(kind=kind, severity=severity or default_sev, message=text, start=now,
                            value=value, limit=limit, joint=joint)
        self._open[key] = _Open(event, now)
        self._new.append(event)

    def instant(self, kind: str, now: float, message: str | None = None, severity: str | None = None,
                value: float | None = None, limit: float | None = None, joint: int | None = None) -> None:
        """A one-off event (a state transition, a refused request): emitted closed, never coalesced."""
        default_sev, meaning = KINDS.get(kind, (WARNING, kind))
        self._new.append(SafetyEvent(kind=kind, severity=severity or default_sev, message=message or meaning,
                                     start=now, end=now, value=value, limit=limit, joint=joint))

    def active(self, kind: str, joint: int | None = None) -> bool:
        return (kind, joint) in self._open

    def flush(self, now: float, force: bool = False) -> tuple[SafetyEvent, ...]:
        if not self._open and not self._new:
            return self._EMPTY
        out = self._new
        self._new = []
        closed = [k for k, r in self._open.items() if force or now - r.last > self.gap]
        for key in closed:
            out.append(self._closed(self._open.pop(key)))
        return tuple(out) if out else self._EMPTY

    @staticmethod
    def _closed(rec: _Open) -> SafetyEvent:
        ev = rec.event
        return replace(ev, end=rec.last, count=rec.count, value=rec.value, limit=rec.limit,
                       message=ev.message + f" ({rec.count} cycles, {rec.last - ev.start:.3f} s)")

    def close_all(self, now: float) -> tuple[SafetyEvent, ...]:
        return self.flush(now, force=True)

    @property
    def open_events(self) -> tuple[SafetyEvent, ...]:
        return tuple(r.event for r in self._open.values())


__all__ = ["SafetyEvent", "EventCoalescer", "KINDS", "SEVERITIES", "INFO", "WARNING", "ERROR", "CRITICAL"]
