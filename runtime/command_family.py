"""The task family a command runs as: that of the bundle's closest trained instruction.

Why one place: the family picks a command's pace, its phases, its queries and its chunk steps, and the policy node
judges it from the text alone (it is told no task). `sudd eval` judges it the same way, so a phrasing the data never
used is measured as the robot would run it: "push the drawer in" is closest to "pull the drawer open" (cosine 0.85)
and runs as drawer_open, its pace and queries too.
"""

from __future__ import annotations

from sim.tasks import task_of_instruction


def command_family(bundle, text: str) -> str | None:
    """The family of the trained instruction closest to `text`; None for a bundle that records no instructions
    or one whose closest instruction no family phrases."""
    best, _ = bundle.task_similarity(text)
    return task_of_instruction(best) if best else None
