"""Open or close the drawer of a cabinet: "open the drawer" / "close the drawer".

Open/closed follow the SUDD rule: the slide joint within 20 % of its upper/lower limit.
"""

from __future__ import annotations

import numpy as np

from sim import objects as obj
from sim.dr_config import DRConfig
from sim.objects import Placement
from sim.tasks.base import Holdout, TaskFamily, TaskInstance, sample_objects, sample_slots
from sim.tasks.scripted import Scripted, top_down

CABINET = "cabinet"
SLIDE = f"{CABINET}/slide"
TRAVEL = 0.16
CABINET_RGBS = ((0.62, 0.5, 0.36, 1), (0.8, 0.8, 0.78, 1), (0.35, 0.4, 0.45, 1))
OPEN_FRACTION = 0.8
CLOSED_FRACTION = 0.2


def sample_cabinet(rng: np.random.Generator, dr: DRConfig) -> dict:
    side = float(rng.choice([-1.0, 1.0]))
    jitter = dr.objects.xy_jitter
    return {"x": side * 0.2 + rng.uniform(-jitter, jitter) * 0.5, "y": 0.63 + rng.uniform(-jitter, jitter) * 0.3,
            "yaw": float(rng.uniform(-1, 1) * min(0.2, dr.objects.yaw_jitter * 0.1)),
            "rgba": list(CABINET_RGBS[int(rng.integers(len(CABINET_RGBS)))])}


def build_cabinet(spec, cab: dict) -> None:
    obj.add_drawer_cabinet(spec, CABINET, Placement(cab["x"], cab["y"], cab["yaw"]), cab["rgba"], travel=TRAVEL)


def distractor_region(cab: dict):
    """The half of the table away from the cabinet."""
    return ((-0.3, -0.05), (0.3, 0.55)) if cab["x"] > 0 else ((0.05, 0.3), (0.3, 0.55))


def set_drawer(world, opening: float) -> None:
    adr = world.model.jnt_qposadr[world.model.joint(SLIDE).id]
    world.data.qpos[adr] = opening
    world.forward()


def drawer_fraction(state) -> float:
    return state.joint_fraction(SLIDE)


def move_drawer(arm: Scripted, state, to_fraction: float) -> None:
    """Grasp the handle from above, slide it along the drawer axis to `to_fraction` of travel, let go."""
    handle = state._d.site_xpos[state._m.site(f"{CABINET}/handle_site").id].copy()
    axis = state.rotation(CABINET) @ np.array([0.0, -1.0, 0.0])  # the direction the drawer opens
    yaw = float(np.arctan2(axis[1], axis[0]))  # fingers close along the pull axis, around the bar
    yaw = arm.best_yaw(yaw)
    arm.gripper(0.5, 0.05)  # half open fits between handle and drawer front
    arm.move_pose(top_down(handle + [0, 0, 0.1], yaw))
    arm.move_pose(top_down(handle + [0, 0, 0.004], yaw), straight=True)
    arm.gripper(1.0, 0.5)
    delta = (to_fraction - drawer_fraction(state)) * TRAVEL
    arm.move_pose(top_down(handle + axis * delta + [0, 0, 0.004], yaw), straight=True)
    arm.gripper(0.4, 0.4)
    end = handle + axis * delta
    arm.move_pose(top_down(end + [0, 0, 0.1], yaw), straight=True)


class DrawerOpen(TaskFamily):
    name = "drawer_open"
    description = "Open the cabinet's drawer."
    templates = ("open the drawer", "pull the drawer open", "open the cabinet drawer")
    paraphrases = ("slide the drawer open", "could you open the drawer", "pull out the drawer")

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        cab = sample_cabinet(rng, dr)
        n = int(rng.integers(0, 3))
        objects = sample_objects(rng, dr, holdout, n, sample_slots(rng, dr, n, distractor_region(cab))) if n else []
        params = {"cabinet": cab, "initial": float(rng.uniform(0.0, 0.1) * TRAVEL)}
        return TaskInstance(self.name, self.phrase(rng), objects, params)

    def build(self, spec, inst: TaskInstance) -> None:
        super().build(spec, inst)
        build_cabinet(spec, inst.params["cabinet"])

    def initialize(self, world, inst: TaskInstance) -> None:
        set_drawer(world, inst.params["initial"])

    def success(self, state, inst: TaskInstance) -> bool:
        return drawer_fraction(state) >= OPEN_FRACTION

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        arm = Scripted(world, observer=observer)
        move_drawer(arm, StateView(world), 1.0)
        arm.hold(0.3)


class DrawerClose(DrawerOpen):
    name = "drawer_close"
    description = "Close the cabinet's open drawer."
    templates = ("close the drawer", "push the drawer shut", "shut the cabinet drawer")
    paraphrases = ("slide the drawer closed", "could you close the drawer", "push the drawer in")

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        inst = super().sample(rng, dr, holdout)
        inst.family = self.name
        inst.instruction = self.phrase(rng)
        inst.params["initial"] = float(rng.uniform(0.6, 1.0) * TRAVEL)
        return inst

    def success(self, state, inst: TaskInstance) -> bool:
        return drawer_fraction(state) <= CLOSED_FRACTION

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        from sim.state import StateView

        arm = Scripted(world, observer=observer)
        move_drawer(arm, StateView(world), 0.0)
        arm.hold(0.3)
