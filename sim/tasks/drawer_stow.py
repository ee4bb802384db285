"""Put the named object in a drawer that is already open: "pick up the red block and put it in the open drawer".

Why a family of its own: it is drawer_put's middle, as a skill that starts where every other family's data does,
at the arm's start pose. Run inside drawer_put (runtime/phases.py), the arm goes back to its start pose once the
drawer is open, and the images there (an open drawer, objects on the table, the arm at home) are a start the
language tells apart from "close the drawer"'s, as it tells pick_place's from stack's. Started at the handle it
has just let go, drawer_put's middle looked to the policy like the start of the closing cycle, and it went back
to the handle (policy/EXPERIMENTS.md, "drawer_put's middle cycle under a text of its own").
"""

from __future__ import annotations

import numpy as np

from sim.dr_config import DRConfig
from sim.tasks.base import Holdout, TaskInstance, sample_objects, sample_slots
from sim.tasks.drawer import CABINET, OPEN_FRACTION, TRAVEL, DrawerOpen, distractor_region, sample_cabinet
from sim.tasks.pick_place import grasp_yaw
from sim.tasks.scripted import Scripted


class StowInOpenDrawer(DrawerOpen):  # its cabinet, built and opened as DrawerOpen's
    name = "drawer_stow"
    description = "Put the named object in the cabinet's open drawer (the drawer starts open and stays so)."
    templates = (
        "pick up the {obj} and put it in the open drawer",
        "put the {obj} in the open drawer",
        "place the {obj} inside the open drawer",
    )
    paraphrases = (
        "could you put the {obj} into the open drawer",
        "stow the {obj} in the open drawer",
    )
    max_seconds = 30.0

    def fields(self, inst: TaskInstance) -> dict[str, str]:
        return {"obj": inst.obj(inst.params["target"]).phrase}

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        cab = sample_cabinet(rng, dr)
        n = int(rng.integers(1, 4))
        objects = sample_objects(rng, dr, holdout, n, sample_slots(rng, dr, n, distractor_region(cab)),
                                 target_shapes=("block", "cylinder"))
        # as open as drawer_open leaves it, or as a policy's opening that just counts as open
        params = {"cabinet": cab, "target": objects[0].name,
                  "initial": float(rng.uniform(OPEN_FRACTION + 0.05, 1.0) * TRAVEL)}
        return TaskInstance(self.name, self.phrase(rng, obj=objects[0].phrase), objects, params)

    def success(self, state, inst: TaskInstance) -> bool:
        target = inst.params["target"]
        return state.inside(target, CABINET) and not state.holding(target)

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        state = StateView(world)
        arm = Scripted(world, observer=observer)
        target = inst.obj(inst.params["target"])
        arm.pick(state.position(target.name), grasp_yaw(target, state.rotation(target.name)))
        lo, hi = state.aabb(f"{CABINET}/inside")
        centre = (lo + hi) / 2
        arm.place(np.array([centre[0], centre[1], lo[2] + target.half_height + 0.03]), 0.0, approach=0.14)
        arm.hold(0.3)
