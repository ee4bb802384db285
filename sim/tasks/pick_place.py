"""Pick-and-place into one of several bins, with distractors: "put the red block in the left bin".

Left and right are as the operator sees them in the scene camera (which faces the robot): "left" is +x.
"""

from __future__ import annotations

import numpy as np

from sim import objects as obj
from sim.dr_config import DRConfig
from sim.objects import Placement
from sim.tasks.base import Holdout, TaskFamily, TaskInstance, sample_objects, sample_slots
from sim.tasks.scripted import Scripted

BIN_INNER = (0.065, 0.075, 0.035)
BIN_Y = 0.64
BIN_LAYOUTS = {2: (("left", 0.16), ("right", -0.16)), 3: (("left", 0.24), ("middle", 0.0), ("right", -0.24))}
BIN_COLORS = ((0.35, 0.35, 0.38, 1), (0.45, 0.33, 0.22, 1), (0.2, 0.28, 0.4, 1))
OBJECT_REGION = ((-0.28, 0.28), (0.30, 0.50))


def grasp_yaw(o, rotation) -> float:
    """Fingers close along the tool x axis: across a bar's narrow side, along a block's x face."""
    yaw = float(np.arctan2(rotation[1, 0], rotation[0, 0]))
    return yaw + (np.pi / 2 if o.shape == "bar" else 0.0)


def footprint_period(obj) -> float | None:
    """The smallest turn about the vertical that maps the object's footprint onto itself; None for a round one."""
    if obj.shape in ("cylinder", "ball"):
        return None
    sx, sy = obj.size[:2]
    return np.pi / 2 if abs(sx - sy) <= 0.05 * max(sx, sy) else np.pi


class PickPlace(TaskFamily):
    name = "pick_place"
    description = "Pick one object among distractors and put it in the named bin."
    templates = (
        "put the {obj} in the {bin} bin",
        "place the {obj} into the {bin} bin",
        "move the {obj} to the {bin} bin",
        "pick up the {obj} and drop it in the {bin} bin",
    )
    paraphrases = (
        "could you put the {obj} into the {bin} bin",
        "the {obj} goes in the {bin} bin",
        "grab the {obj} and leave it in the {bin} bin",
        "transfer the {obj} to the {bin} container",
    )

    def fields(self, inst: TaskInstance) -> dict[str, str]:
        return {"obj": inst.obj(inst.params["target"]).phrase, "bin": inst.params["bin"].removeprefix("bin_")}

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        n_bins = int(rng.choice([2, 3]))
        n_objects = int(rng.integers(2, 5))  # the target plus 1-3 distractors
        slots = sample_slots(rng, dr, n_objects, OBJECT_REGION)
        objects = sample_objects(rng, dr, holdout, n_objects, slots)
        bins = [(name, x + rng.uniform(-1, 1) * dr.objects.xy_jitter * 0.3) for name, x in BIN_LAYOUTS[n_bins]]
        target_bin = str(rng.choice([b for b, _ in bins]))
        target = objects[0]
        text = self.phrase(rng, obj=target.phrase, bin=target_bin)
        params = {"target": target.name, "bin": f"bin_{target_bin}", "bins": [[b, float(x)] for b, x in bins]}
        return TaskInstance(self.name, text, objects, params)

    def build(self, spec, inst: TaskInstance) -> None:
        super().build(spec, inst)
        for i, (name, x) in enumerate(inst.params["bins"]):
            obj.add_bin(spec, f"bin_{name}", BIN_INNER, BIN_COLORS[i % len(BIN_COLORS)], Placement(x, BIN_Y))

    def success(self, state, inst: TaskInstance) -> bool:
        target = inst.params["target"]
        return (state.inside(target, inst.params["bin"]) and not state.holding(target)
                and float(np.linalg.norm(state.velocity(target))) < 0.05)

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        state = StateView(world)
        target = inst.obj(inst.params["target"])
        arm = Scripted(world, observer=observer)
        pos = state.position(target.name)
        arm.pick(pos, grasp_yaw(target, state.rotation(target.name)))
        bin_pos = state.position(inst.params["bin"])
        drop = bin_pos + [0.0, 0.0, 0.008 + target.half_height + 0.04]
        arm.place(drop, 0.0)
        arm.hold(0.5)
