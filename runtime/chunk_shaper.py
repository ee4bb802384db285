"""What the runtime does to the policy's chunks between the denoiser and the controller, for one command.

The steps, in this order, each its own module with its own reasons: the coherent pick among the samples drawn
(policy/coherence.py), the served pause (runtime/served_pause.py), the wrist turn (runtime/wrist_turn.py), the grasp
steer (runtime/grasp_steer.py), the release guard (runtime/release_guard.py), the handle height
(runtime/handle_height.py), the empty close (runtime/empty_close.py) and the finger wait (runtime/finger_wait.py).
The runtime's policy node and `sudd eval` both run them through this class, so that what is evaluated is what runs
on the robot. Only the policy's own chunks
go through it: a look's or a phase retreat's moves do not (`forget` then, so the next pick starts afresh).

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.coherence import Coherence
from policy.stage import GRIPPER_COLUMN
from runtime.empty_close import EmptyClose
from runtime.finger_wait import FingerWait
from runtime.grasp_steer import GraspSteer
from runtime.handle_height import HandleHeight
from runtime.release_guard import ReleaseGuard
from runtime.served_pause import ServedPause
from runtime.shaping import Shaping
from runtime.wrist_turn import steer


# The operator's word the first time a step changes a command's chunks: (step, its count, event kind, message).
FIRST_WORDS = (
    ("regrasp", "steered", "policy_grasp_steer", "the fingers closed on nothing: the retry is moved over the object "
     "the object query located"),
    ("guard", "held", "policy_release_guard", "the policy opened the fingers on the object far from where it goes: "
     "held closed and carried towards it"),
    ("level", "kept", "policy_handle_height", "the chunks left the height the fingers closed on the drawer's handle "
     "at: kept there while they hold it"),
    ("empty", "opened", "policy_empty_close", "the fingers stood shut on nothing: opened where they are, as the data "
     "collector reopens after a missed grasp"),
)


class ChunkShaper:
    """One command's steps (module doc). `turn` is the command's policy.turn_query.TurnQuery."""

    def __init__(self, turn, shaping: Shaping = Shaping()):
        self.turn = turn
        self.coherence = Coherence(shaping.samples)
        self.pause = ServedPause(enabled=shaping.served_pause)
        self.wait = FingerWait(enabled=shaping.finger_wait)
        self.regrasp = GraspSteer(enabled=shaping.grasp_steer)
        self.guard = ReleaseGuard(enabled=shaping.release_guard)
        self.level = HandleHeight(enabled=shaping.handle_height)
        self.empty = EmptyClose(enabled=shaping.empty_close)
        self.firsts: list[tuple[str, str]] = []  # (event kind, message) of the steps that first acted at this tick

    def chunk(self, chunks: np.ndarray, images: dict, proprio: np.ndarray, stage: int, objects, request: float,
              family: str | None, t_obs: float, dt: float, speed: float) -> np.ndarray:
        """The (n, 10) actions to send, from the (K, n, 10) chunks sampled at this tick (the executed rows).
        `proprio` the window (To, Dp), its newest row the TCP pose and measured closure now; `stage` the grasp
        cycles completed; `objects` the command's policy.object_query.ObjectQuery; `request` the gripper's standing
        position request; `family` the running skill's; `t_obs` [s] the observation's time; `dt` [s] between
        actions; `speed` the pace (a fraction of the recorded one)."""
        before = [getattr(getattr(self, step), count) for step, count, _, _ in FIRST_WORDS]
        now = proprio[-1]
        closure = float(now[GRIPPER_COLUMN])
        a = self.coherence.pick(chunks, t_obs, dt)
        a = self.pause.chunk(a, now, request, t_obs, speed=speed)
        a = steer(self.turn, a, images, proprio, stage, request >= 0.5, dt)
        a = self.regrasp.chunk(a, objects, stage, request, dt)
        a = self.guard.chunk(a, objects, stage, request, closure, dt)
        a = self.level.chunk(a, family, request, closure, float(now[2]))
        a = self.empty.chunk(a, request, closure, t_obs)
        self.firsts = [(kind, words) for (step, count, kind, words), n in zip(FIRST_WORDS, before)
                       if getattr(getattr(self, step), count) and not n]
        return self.wait.chunk(a, now, t_obs)

    def forget(self) -> None:
        """A move not the policy's ran at this tick (a look, a retreat): the next pick has no chunk to go on from."""
        self.coherence.forget()


__all__ = ["ChunkShaper"]
