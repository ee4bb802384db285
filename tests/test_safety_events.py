"""safety.events: interventions coalesced into episodes with a duration; JSON round trip."""

from __future__ import annotations

import json
import math

from safety.events import EventCoalescer, SafetyEvent


def test_repeated_intervention_is_one_event_with_a_duration():
    ev = EventCoalescer(gap=0.1)
    out = []
    for k in range(500):  # one second of a limit held at 500 Hz
        now = k * 0.002
        ev.report("velocity", now, value=1.0 + k * 1e-3, limit=1.0)
        out += ev.flush(now)
    for k in range(500, 600):
        out += ev.flush(k * 0.002)
    assert len(out) == 2
    opened, closed = out
    assert opened.ongoing and opened.kind == "velocity" and opened.start == 0.0
    assert not closed.ongoing and closed.count == 500
    assert math.isclose(closed.duration, 0.998) and math.isclose(closed.value, 1.499)


def test_separate_joints_and_kinds_are_separate_events_and_gaps_split_episodes():
    ev = EventCoalescer(gap=0.05)
    ev.report("joint_position", 0.0, value=3.2, limit=3.09, joint=2)
    ev.report("joint_position", 0.0, value=-7.0, limit=-6.23, joint=0)
    ev.report("jerk", 0.0, value=3.0, limit=1.0)
    assert len(ev.flush(0.0)) == 3
    ev.report("jerk", 0.2, value=2.0, limit=1.0)  # after a gap: a new episode
    out = ev.flush(0.2)
    kinds = sorted((e.kind, e.ongoing) for e in out)
    assert ("jerk", True) in kinds and ("jerk", False) in kinds and len([k for k in kinds if not k[1]]) == 3


def test_quiet_cycles_cost_nothing():
    ev = EventCoalescer()
    assert ev.flush(0.0) == () and ev.flush(1.0) is ev.flush(2.0)


def test_instant_events_and_json_round_trip():
    ev = EventCoalescer()
    ev.instant("recovery", 1.5, message="re-armed")
    ev.report("collision", 1.5, value=float("inf"), limit=0.03)
    out = ev.flush(1.5)
    assert out[0].end == 1.5 and out[0].duration == 0.0
    for e in out:
        d = json.loads(e.to_json())
        assert set(d) >= {"kind", "severity", "message", "value", "limit", "start", "end", "duration", "count"}
        back = SafetyEvent.from_dict(d)
        assert back.kind == e.kind and (back.value == e.value or math.isinf(back.value))
    assert SafetyEvent("x", "info", "m", 0.0).__hash__  # frozen, hashable
