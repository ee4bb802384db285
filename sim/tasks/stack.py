"""Stacking: "stack the red block on the blue block", among 0-2 other blocks."""

from __future__ import annotations

import numpy as np

from sim.dr_config import DRConfig
from sim.tasks.base import Holdout, TaskFamily, TaskInstance, sample_objects, sample_slots
from sim.tasks.pick_place import grasp_yaw
from sim.tasks.scripted import Scripted

REGION = ((-0.25, 0.25), (0.32, 0.62))


class Stack(TaskFamily):
    name = "stack"
    description = "Put one block on top of another."
    templates = (
        "stack the {top} on the {bottom}",
        "put the {top} on top of the {bottom}",
        "place the {top} onto the {bottom}",
    )
    paraphrases = (
        "set the {top} down on the {bottom}",
        "pile the {top} on the {bottom}",
        "could you put the {top} onto the {bottom}",
    )

    novel_shapes = ()

    def fields(self, inst: TaskInstance) -> dict[str, str]:
        return {"top": inst.obj(inst.params["top"]).phrase, "bottom": inst.obj(inst.params["bottom"]).phrase}

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        n = int(rng.integers(2, 5))
        slots = sample_slots(rng, dr, n, REGION, min_gap=0.1)
        objects = sample_objects(rng, dr, holdout, n, slots, target_shapes=("block",), novel_shapes=self.novel_shapes)
        # The base of the stack is a block too: pick it among the others, or make the second one a block.
        others = [o for o in objects[1:] if o.shape == "block"]
        if not others:
            from dataclasses import replace

            objects[1] = replace(objects[1], shape="block", size=objects[0].size)
            others = [objects[1]]
        bottom = others[int(rng.integers(len(others)))]
        text = self.phrase(rng, top=objects[0].phrase, bottom=bottom.phrase)
        return TaskInstance(self.name, text, objects, {"top": objects[0].name, "bottom": bottom.name})

    def success(self, state, inst: TaskInstance) -> bool:
        top, bottom = inst.params["top"], inst.params["bottom"]
        return (state.on_top(top, bottom) and not state.holding(top)
                and float(np.linalg.norm(state.velocity(top))) < 0.05)

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        state = StateView(world)
        top, bottom = inst.obj(inst.params["top"]), inst.obj(inst.params["bottom"])
        arm = Scripted(world, observer=observer)
        arm.pick(state.position(top.name), grasp_yaw(top, state.rotation(top.name)))
        lower = state.position(bottom.name)
        drop = lower + [0.0, 0.0, bottom.half_height + top.half_height + 0.012]
        arm.place(drop, grasp_yaw(bottom, state.rotation(bottom.name)), approach=0.1)
        arm.hold(0.5)
