"""Long horizon: "put the red block in the drawer and close it" (open, pick, place inside, close)."""

from __future__ import annotations

import numpy as np

from sim.dr_config import DRConfig
from sim.tasks.base import Holdout, TaskFamily, TaskInstance, sample_objects, sample_slots
from sim.tasks.drawer import (CABINET, CLOSED_FRACTION, build_cabinet, distractor_region, drawer_fraction,
                              move_drawer, sample_cabinet)
from sim.tasks.pick_place import grasp_yaw
from sim.tasks.scripted import Scripted


class PutInDrawer(TaskFamily):
    name = "drawer_put"
    description = "Open the drawer, put the named object inside, and close it."
    templates = (
        "put the {obj} in the drawer and close it",
        "place the {obj} inside the drawer, then close the drawer",
        "store the {obj} in the drawer and shut it",
    )
    paraphrases = (
        "put away the {obj} in the drawer and close the drawer",
        "could you stow the {obj} in the drawer and close it",
    )

    def fields(self, inst: TaskInstance) -> dict[str, str]:
        return {"obj": inst.obj(inst.params["target"]).phrase}
    max_seconds = 60.0

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        cab = sample_cabinet(rng, dr)
        n = int(rng.integers(1, 4))
        objects = sample_objects(rng, dr, holdout, n, sample_slots(rng, dr, n, distractor_region(cab)),
                                 target_shapes=("block", "cylinder"))
        text = self.phrase(rng, obj=objects[0].phrase)
        return TaskInstance(self.name, text, objects, {"cabinet": cab, "target": objects[0].name})

    def build(self, spec, inst: TaskInstance) -> None:
        super().build(spec, inst)
        build_cabinet(spec, inst.params["cabinet"])

    def success(self, state, inst: TaskInstance) -> bool:
        target = inst.params["target"]
        return (state.inside(target, CABINET) and drawer_fraction(state) <= CLOSED_FRACTION
                and not state.holding(target))

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        state = StateView(world)
        arm = Scripted(world, observer=observer)
        move_drawer(arm, state, 1.0)
        target = inst.obj(inst.params["target"])
        arm.pick(state.position(target.name), grasp_yaw(target, state.rotation(target.name)))
        lo, hi = state.aabb(f"{CABINET}/inside")
        centre = (lo + hi) / 2
        drop = np.array([centre[0], centre[1], lo[2] + target.half_height + 0.03])
        arm.place(drop, 0.0, approach=0.14)
        move_drawer(arm, state, 0.0)
        arm.hold(0.3)
