"""How fast the arm follows the policy: its chunks' actions spaced 1 / (control_hz x speed) apart.

The speed is per task family (policy.pace: the bundle's `pace` table, `--speed` on top). Only the execution
slows: the observation history stays 1 / control_hz apart, the spacing the policy was trained on, so it sees
the motions it knows, slower.
"""

from __future__ import annotations

from policy.pace import Pace, bundle_pace, check_speed, parse_pace


def action_period_ns(control_hz: float, speed: float) -> int:
    """Nanoseconds between a chunk's actions (and between the policy's ticks) at `speed`."""
    return int(round(1e9 / (control_hz * check_speed(speed))))


def check_speed_spec(spec: str | None) -> dict[str, float]:
    """`--speed` checked before anything starts ({} when not given: the bundle's pace)."""
    from sim.tasks import task_names

    return parse_pace(spec, task_names()) if spec not in (None, "") else {}


def resolve_pace(manifest: dict, spec: str | None) -> Pace:
    """The bundle's pace with `--speed` on top."""
    return bundle_pace(manifest).overridden(check_speed_spec(spec))


def command_speed(pace: Pace, instruction: str | None) -> tuple[str | None, float]:
    """(the family of a trained instruction, the speed it plays at)."""
    from sim.tasks import task_of_instruction

    task = task_of_instruction(instruction) if instruction else None
    return task, pace.speed(task)
