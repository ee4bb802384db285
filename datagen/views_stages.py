"""Views on the way to a long task's later grasps: drawer_put grasps the handle (to open the drawer), then the
object (to put it inside), then the handle again (to close it); see datagen/views.py for the views themselves.

Why: drawer_put's views showed only the first approach, to the shut drawer's handle. The policy's aux head,
pretrained on them, is 2.2 cm off the handle before the first grasp and 25 cm off the object before the second
(worse than a constant guess, 10 cm), and in closed loop the shipped policy opens the drawer in 12 of 20 seeds
and then goes back to the handle every time (policy/EXPERIMENTS.md, "drawer_put: the head points at the handle
after the drawer is open"). A stage's views put the scene where the collector leaves it before that grasp (the
drawer open to the collector's target; for `close`, the object in it) and the arm on its way there from where
the last release left it, labelled with that grasp's and its release's points.

A label set is named by its key: the family for the first stage (so the views rendered before stages keep
their name), `family/stage` for a later one ("drawer_put/object"); offsets are measured per key, on the
recorded cycle of that stage (`datagen.views.measure_offsets`).
"""

from __future__ import annotations

import numpy as np

from datagen.articulated import OPEN_TARGET
from datagen.view_anchors import HANDLE, Anchors, anchors, drop_point, object_to_drawer
from datagen.views_carry import free_qpos
from sim.state import StateView
from sim.tasks.drawer import SLIDE, set_drawer

STAGES = {"drawer_put": ("handle", "object", "close")}  # a long task's grasps, in the collector's order
# the grasp cycle whose object lies where it starts, so it can be found from the start (`sudd views --at-home`,
# the object locator): drawer_put's after the handle, drawer_stow's first (the drawer is open already)
OBJECT_AT_START = {"drawer_put": 1, "drawer_stow": 0}
ABOVE_HANDLE = 0.10  # the collector lets go of the handle and rises this far before it moves on
ABOVE_DROP = 0.14  # the place primitive's approach height above the drop (sim/tasks/drawer_put.py)


def stages(task: str) -> tuple[str, ...]:
    """The stages a family's views can show: its grasps in order (one, unnamed-first, for most families)."""
    return STAGES.get(task, ("",))


def label_key(task: str, stage: str = "") -> str:
    """The key a view's labels are measured and looked up under: the family, or `family/stage` after the first."""
    names = stages(task)
    if stage and stage not in names:
        raise ValueError(f"stage {stage!r} of {task}: expected one of {', '.join(n for n in names if n) or 'none'}"
                         f"{'' if task in STAGES else f' ({task} grasps once; leave the stage out)'}")
    return task if not stage or names.index(stage) == 0 else f"{task}/{stage}"


def parse_key(key: str) -> tuple[str, int]:
    """A label key -> (family, index of its stage: which of the episode's grasp cycles it labels)."""
    task, _, stage = key.partition("/")
    return task, stage_index(task, stage)


def stage_index(task: str, stage: str = "") -> int:
    """Which of the family's grasp cycles `stage` is (0 for the first, or none named); refuses an unknown one."""
    label_key(task, stage)
    return stages(task).index(stage) if stage else 0


def set_stage(ep, stage: int) -> None:
    """Put a built drawer_put scene where the collector leaves it before grasp `stage`: the drawer open to its
    target from the second grasp on, and for the third the object lying in it."""
    if stage == 0:
        return
    world = ep.world
    lo, hi = StateView(world).joint_range(SLIDE)
    set_drawer(world, lo + OPEN_TARGET * (hi - lo))
    if stage == 2:
        name = ep.instance.params["target"]
        free = free_qpos(world, name)
        p = drop_point(ep) + [0.0, 0.0, ep.instance.obj(name).half_height + 1e-3]
        world.data.qpos[free.start:free.start + 3] = p
        world.data.qvel[:] = 0.0
        world.forward()


def stage_anchors(ep, stage: int) -> Anchors:
    """The anchors of grasp `stage` in a scene set_stage has put there: the object and the open drawer's floor
    for the second, the open drawer's handle and where it is shut for the third (as for the first)."""
    return anchors(ep) if stage != 1 else object_to_drawer(ep)


def start_pose(ep, home: np.ndarray, stage: int) -> np.ndarray:
    """The TCP pose a stage's views set out from (the first view is there): home for the first grasp; above the
    opened handle, where the arm let go of it, for the second; above the drop for the third."""
    if stage == 0:
        return home
    T = home.copy()
    T[:3, 3] = (StateView(ep.world).position(HANDLE) + [0.0, 0.0, ABOVE_HANDLE] if stage == 1
                else drop_point(ep) + [0.0, 0.0, ABOVE_DROP])
    return T
