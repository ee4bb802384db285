"""A long command run as skills the policy has, one after another: its phases.

Why: drawer_put is "open the drawer", take the object to it, "close the drawer", and two of those are whole
task families the distilled policy does well at their own pace (drawer_open at 0.75, drawer_close at 0.5),
where the same policy given drawer_put's one command opens the drawer at full speed 12 times in 20 and never
completes it (policy/EXPERIMENTS.md, "drawer_put as three skills the policy has"). The phase is the number of
grasp cycles completed since the command started (policy.stage.GraspCycles: the handle let go, then the
object), a signal a real 2F-85 gives as well as the sim, so no success check or privileged state decides it.

A phase's text None stands for the command itself, a text with "{obj}" for the phase's own text with the
command's object (policy.phased.OWN_PHASE_TEXT, for a bundle taught it); its family names the pace (the bundle's
pace table) the arm plays that phase at.
"""

from __future__ import annotations

from dataclasses import dataclass

from policy.pace import Pace
from policy.phased import OWN_PHASE_TEXT, PHASED, fill_object, own_texts_taught


# `sudd eval --phases/--no-phases`, `sudd run --phases/--no-phases`
HELP = ("run a long command as the skills it is made of (runtime/phases.py; drawer_put: open the drawer, take the "
        "object, close the drawer), switched by the gripper's grasp cycles, each at its family's pace; "
        "--no-phases: every command as one. Default: the families the bundle's manifest lists (`phased`)")


@dataclass(frozen=True)
class Phase:
    text: str | None  # None: the command itself; with "{obj}": the command's object filled in
    speed: float
    # The grasp cycles the policy is told are this count less (policy.stage): a skill of another family counts
    # its own cycles from 0, as that family's data did; the command itself counts as its own data did.
    stage_from: int = 0


def phases_for(task: str, pace: Pace, instructions=()) -> list[Phase]:
    """The phases of family `task` at the bundle's pace (a ValueError for a family run as one command); a phase
    of the command's own family gets its own text where the bundle's trained `instructions` hold it."""
    if task not in PHASED:
        raise ValueError(f"phases: the family {task!r} is run as one command; phased families: {', '.join(PHASED)}")
    own = OWN_PHASE_TEXT.get(task, {}) if own_texts_taught(task, instructions) else {}
    return [Phase(text if text is not None else own.get(i), pace.speed(family), 0 if family == task else i)
            for i, (text, family) in enumerate(PHASED[task])]


def phase_at(phases: list[Phase], grasp_cycles: int) -> int:
    """The phase running after `grasp_cycles` completed cycles (the last one stays once reached)."""
    return min(max(int(grasp_cycles), 0), len(phases) - 1)


class Sequencer:
    """The phases of one command as it runs: which one the grasp cycles so far select, its text embedding and
    speed. `update` says when the phase changed (the caller then re-times its ticks and says so)."""

    def __init__(self, phases: list[Phase], embed, command_embedding, command: str = ""):
        self.phases = phases
        # an own text the command names no object for (a free phrasing) falls back to the command itself
        self.texts = [p.text if p.text is None or "{obj}" not in p.text else fill_object(p.text, command)
                      for p in phases]
        self.embeddings = [command_embedding if t is None else embed(t) for t in self.texts]
        self.index: int | None = None

    def update(self, grasp_cycles: int) -> bool:
        k = phase_at(self.phases, grasp_cycles)
        changed, self.index = k != self.index, k
        return changed

    @property
    def embedding(self):
        return self.embeddings[self.index or 0]

    def stage(self, grasp_cycles: int) -> int:
        """The grasp cycles to tell the policy in the phase running (Phase.stage_from)."""
        return max(int(grasp_cycles) - self.phases[self.index or 0].stage_from, 0)

    @property
    def speed(self) -> float:
        return self.phases[self.index or 0].speed

    def describe(self, command: str) -> str:
        """'phase 2 of 3: "<text>" at speed 1' for the phase running."""
        k = self.index or 0
        return f"phase {k + 1} of {len(self.phases)}: '{self.texts[k] or command}' at speed {self.phases[k].speed:g}"

