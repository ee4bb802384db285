"""Why a closed-loop episode failed: what the gripper held along the way, read from the sim at every tick.

A success rate says how often; this says where a policy goes wrong, which is what decides the next
experiment (more data? better grounding? finer placing?). The classes, in the order a pick-and-place
episode could reach them:

    no_grasp          the gripper never held any object
    wrong_object      it held an object, never the one the command named
    target_not_placed it held the named object, but the episode ended without the task's success
                      (dropped on the way, released outside the goal, or stopped while carrying it)

An episode that ends in a protective stop also keeps its stop as `end`, so the two read together:
"protective_stop + wrong_object". Tasks without a named object (open a drawer) report only no_grasp.

`closest_m` grades a no_grasp: how near the TCP came to the named object before it first held it. A blind
policy that drives to the average target stays 10-20 cm away; one that sees closes to within a few cm and
misses by a finger's width. Success rates of 0 % cannot tell those apart.
"""

from __future__ import annotations

import numpy as np

from sim.state import StateView

FAILURES = ("no_grasp", "wrong_object", "target_not_placed")


def target_name(inst) -> str | None:
    """The object the command names (pick_place, drawer_put: target; stack: the one to put on top)."""
    return inst.params.get("target") or inst.params.get("top")


class GraspProgress:
    """An observer for `run_policy_episode`: call it with (world, instance) at every policy tick."""

    def __init__(self):
        self.held: list[str] = []  # objects held at some tick, in the order first held
        self.target: str | None = None
        self.closest_m: float | None = None  # TCP to the named object, while the gripper had not yet held it
        self._view = None

    def __call__(self, world, inst) -> None:
        if self._view is None:
            self._view = StateView(world)
            self.target = target_name(inst)
        for o in inst.objects:
            if o.name not in self.held and self._view.holding(o.name):
                self.held.append(o.name)
        if self.target is not None and self.target not in self.held:
            d = float(np.linalg.norm(world.tcp_pose()[:3, 3] - self._view.position(self.target)))
            self.closest_m = d if self.closest_m is None else min(self.closest_m, d)

    def failure(self, success: bool) -> str:
        """One of FAILURES, or "" for a success."""
        if success:
            return ""
        if not self.held:
            return "no_grasp"
        if self.target is not None and self.target not in self.held:
            return "wrong_object"
        return "target_not_placed"
