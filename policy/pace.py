"""The pace a bundle's chunks are played at, per task family: the manifest's `pace` table.

Why per family: the collector slows to 5 cm/s for its last second before a contact; the distilled policy,
replanning every 0.1 s, reaches a drawer's front at 10-25 cm/s and the contact force stops the arm. Played at
half the recorded pace the shipped bundle closes the drawer 20/20 (12/20 at full pace: 8 force stops), but its
pick_place drops from 20/20 to 13/20 (policy/EXPERIMENTS.md, "Half speed"). So the pace is chosen per family,
recorded with the bundle it was measured on, and `--speed` overrides it.

The table maps a family to a speed in [MIN_SPEED, 1] (a fraction of the recorded pace); "*" sets the families
not named; a family in neither plays at 1. A command's family is that of its closest trained instruction
(sim.tasks.task_of_instruction); a command of no known family plays at the "*" speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

MIN_SPEED = 0.1
OTHERS = "*"


def check_speed(speed, what: str = "speed") -> float:
    """The speed as a float in [MIN_SPEED, 1], or a ValueError that says what to give."""
    try:
        s = float(speed)
    except (TypeError, ValueError):
        s = math.nan
    if not (math.isfinite(s) and MIN_SPEED <= s <= 1.0):
        raise ValueError(f"{what} {speed!r}: expected a fraction of the demonstrated pace in [{MIN_SPEED}, 1] "
                         "(1: as recorded; 0.5: half as fast, actions 2 / control_hz apart)")
    return s


def check_pace_table(table, known: Iterable[str], where: str) -> dict[str, float]:
    """A validated {family or "*": speed}; errors name `where`.KEY and what is allowed."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table of task family -> speed, got {type(table).__name__}")
    allowed = sorted(known)
    out = {}
    for key, value in table.items():
        if key != OTHERS and key not in allowed:
            raise ValueError(f"{where}.{key}: unknown task family; expected one of {allowed} or '{OTHERS}' "
                             "(the families not named)")
        out[str(key)] = check_speed(value, f"{where}.{key}")
    return out


def parse_pace(spec: str, known: Iterable[str]) -> dict[str, float]:
    """`--speed` text: "F" (every family at F), or "TASK=F[,TASK=F...]" ("*=F": the families not named)."""
    text = str(spec).strip()
    if "=" not in text:
        return {OTHERS: check_speed(text, "--speed")}
    table = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--speed {spec!r}: expected F or TASK=F[,TASK=F...] (e.g. 0.5, or "
                             "drawer_close=0.5,*=1); the item {item!r} is neither")
        table[key.strip()] = value.strip()
    return check_pace_table(table, known, "--speed")


@dataclass(frozen=True)
class Pace:
    """The speed each task family plays at."""

    table: dict[str, float] = field(default_factory=dict)

    def speed(self, task: str | None) -> float:
        return self.table.get(task, self.table.get(OTHERS, 1.0))  # task None: no family, the "*" speed

    def overridden(self, override: dict[str, float]) -> "Pace":
        """`override` on top: with a "*" entry it replaces the whole table (`--speed 0.5`: every family at 0.5),
        else its families replace theirs."""
        return Pace(dict(override) if OTHERS in override else {**self.table, **override})

    def describe(self) -> str:
        named = ", ".join(f"{k} {v:g}" for k, v in sorted(self.table.items()) if k != OTHERS)
        rest = f"{'others' if named else 'every family'} {self.speed(None):g}"
        return f"{named}, {rest}" if named else rest


def bundle_pace(manifest: dict) -> Pace:
    """The manifest's `pace` (bundles before it: every family at 1)."""
    return Pace(check_pace_table(manifest.get("pace", {}), manifest.get("tasks") or [], "manifest pace"))
