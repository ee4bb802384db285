"""A long command run as skills the policy has, one after another: its phases.

Why: drawer_put is "open the drawer", take the object to it, "close the drawer", and two of those are whole
task families the distilled policy does well at their own pace (drawer_open at 0.75, drawer_close at 0.5),
where the same policy given drawer_put's one command opens the drawer at full speed 12 times in 20 and never
completes it (policy/EXPERIMENTS.md, "drawer_put as three skills the policy has"). The phase is the number of
grasp cycles completed since the command started (policy.stage.GraspCycles: the handle let go, then the
object), a signal a real 2F-85 gives as well as the sim, so no success check or privileged state decides it.

A phase's text None stands for the command itself, a text with "{obj}" for the phase's own text with the
command's object (policy.phased.OWN_PHASE_TEXT, for a bundle taught it); its family names the pace (the bundle's
pace table) the arm plays that phase at. For a bundle taught drawer_stow, drawer_put's middle phase is that
family's skill (policy.phased.SKILL_PHASE): the arm first goes back to where the command started
(runtime/retreat.py), where drawer_stow's data starts, and the skill takes over there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.pace import Pace
from policy.phased import OWN_PHASE_TEXT, PHASED, SKILL_PHASE, fill_object, own_texts_taught
from runtime.retreat import Retreat, arrived, free_fingers, hold_chunk, retreat_chunk


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
    # Whether the arm first goes back to where the command started (runtime/retreat.py), as the skill's data began.
    from_start: bool = False
    family: str = ""  # the family whose skill the phase is (runtime.handle_height: a skill on a drawer's handle)


def phases_for(task: str, pace: Pace, instructions=(), tasks=()) -> list[Phase]:
    """The phases of family `task` at the bundle's pace (a ValueError for a family run as one command); a phase
    of the command's own family is another family's skill, from the start pose, where the bundle's `tasks` hold
    that family (policy.phased.SKILL_PHASE), else gets its own text where the bundle's trained `instructions`
    hold it."""
    if task not in PHASED:
        raise ValueError(f"phases: the family {task!r} is run as one command; phased families: {', '.join(PHASED)}")
    own = OWN_PHASE_TEXT.get(task, {}) if own_texts_taught(task, instructions) else {}
    out = []
    for i, (text, family) in enumerate(PHASED[task]):
        skill = SKILL_PHASE.get(task, {}).get(i)
        if text is None and skill in tasks:
            out.append(Phase(OWN_PHASE_TEXT[task][i], pace.speed(skill), i, from_start=True, family=skill))
        else:
            out.append(Phase(text if text is not None else own.get(i), pace.speed(family), 0 if family == task else i,
                             family=family))
    return out


def phase_at(phases: list[Phase], grasp_cycles: int) -> int:
    """The phase running after `grasp_cycles` completed cycles (the last one stays once reached)."""
    return min(max(int(grasp_cycles), 0), len(phases) - 1)


class Sequencer:
    """The phases of one command as it runs: which one the grasp cycles so far select, its text embedding and
    speed. `update` says when the phase changed (the caller then re-times its ticks and says so); while a phase's
    retreat runs, `retreat` gives the chunk to send instead of the policy's."""

    def __init__(self, phases: list[Phase], embed, command_embedding, command: str = "", retreat: Retreat = Retreat()):
        self.phases = phases
        # an own text the command names no object for (a free phrasing) falls back to the command itself
        self.texts = [p.text if p.text is None or "{obj}" not in p.text else fill_object(p.text, command)
                      for p in phases]
        self.embeddings = [command_embedding if t is None else embed(t) for t in self.texts]
        self.index: int | None = None
        self.cfg = retreat
        self.start: np.ndarray | None = None  # the TCP pose (9,) at the first update: where the command began
        self._waiting: float | None = None  # seconds a retreat has waited for the hand to be empty
        self._free = 0.0
        self._retreating: float | None = None  # seconds the running retreat has taken so far
        self.retreats: list[float] = []  # seconds each finished retreat took

    def update(self, grasp_cycles: int, pose: np.ndarray | None = None) -> bool:
        """The phase for `grasp_cycles`; `pose` the TCP's (position, rot6d), the first one kept as the start."""
        if self.start is None and pose is not None:
            self.start = np.array(pose[:9], np.float64)
        k = phase_at(self.phases, grasp_cycles)
        changed, self.index = k != self.index, k
        if changed:
            self._end_retreat()
            self._waiting = 0.0 if self.phases[k].from_start and self.start is not None else None
            self._free = 0.0  # seconds the fingers have been free while waiting
        return changed

    def retreat(self, pose: np.ndarray, command: float, closure: float, n: int, dt: float) -> np.ndarray | None:
        """(n, 10) actions `dt` s apart while this phase's retreat runs, else None (the policy's turn). The
        gripper's position request `command` and measured `closure` (0 open .. 1 closed) say whether the hand is
        empty: the retreat holds the arm still with the hand told to open for up to cfg.wait_seconds until the
        fingers are at their request (cfg.settle seconds of them), then goes back toward the start, and ends
        there or after cfg.max_seconds."""
        if self._waiting is not None:
            self._free = self._free + dt if free_fingers(command, closure, self.cfg) else 0.0
            if self._free >= self.cfg.settle - 1e-9:  # let go and settled: back to the start from here
                self._waiting, self._retreating = None, 0.0
            else:
                self._waiting += dt
                if self._waiting >= self.cfg.wait_seconds - 1e-9:  # still holding: the skill goes on from here
                    self._waiting = None
                    return None
                return hold_chunk(pose, n)  # still, the hand opening: not the next skill's move yet
        if self._retreating is None:
            return None
        if arrived(pose, self.start, self.cfg) or self._retreating >= self.cfg.max_seconds - 1e-9:
            self._end_retreat()
            return None
        self._retreating += dt
        return retreat_chunk(pose, self.start, command, n, dt, self.cfg)

    @property
    def retreat_seconds(self) -> list[float]:
        """Seconds each retreat took so far, the one running last."""
        running = [] if self._retreating is None else [round(self._retreating, 2)]
        return self.retreats + running

    def _end_retreat(self) -> None:
        if self._retreating is not None:
            self.retreats.append(round(self._retreating, 2))
        self._retreating = None

    @property
    def embedding(self):
        return self.embeddings[self.index or 0]

    def stage(self, grasp_cycles: int) -> int:
        """The grasp cycles to tell the policy in the phase running (Phase.stage_from)."""
        return max(int(grasp_cycles) - self.phases[self.index or 0].stage_from, 0)

    @property
    def family(self) -> str:
        return self.phases[self.index or 0].family

    @property
    def speed(self) -> float:
        return self.phases[self.index or 0].speed

    def describe(self, command: str) -> str:
        """'phase 2 of 3: "<text>" at speed 1' for the phase running."""
        k = self.index or 0
        back = ", from the start pose" if self.phases[k].from_start else ""
        return (f"phase {k + 1} of {len(self.phases)}: '{self.texts[k] or command}' at speed "
                f"{self.phases[k].speed:g}{back}")

