"""Where a scene's grasp and release happen, per task family: the anchors a rendered view's labels hang on.

A view's labels (datagen/views.py) are the grasp and release points the policy's aux head regresses: where the
collector would close the gripper and where it would open it again. They are an anchor in the scene plus an
offset measured on recorded episodes (`datagen.views.measure_offsets`), the offset in the anchor's `frame`:
- pick_place: the named object and its bin, in the world frame (as before the families came).
- stack: the top block and the block it goes on.
- drawer_open, drawer_close, drawer_put: the handle where it is, and where it is with the drawer shut, in the
  cabinet's frame. Why the cabinet's: its yaw is randomized, and the handle travels along the cabinet's own
  axis, so the release (the handle pulled out, or pushed in) is a fixed offset only there. drawer_put's first
  grasp is the handle's (it opens the drawer first); the views of its later grasps (the object, with the
  drawer open; the handle again, to close it) are datagen/views_stages.py's.
- drawer_stow (drawer_put's middle, the drawer open from the start): the object, and the open drawer's floor in
  the cabinet's frame (the drawer's travel is along it, so the release is a fixed offset only there).

The grasp yaw and footprint period feed the grasp-axis label (policy/grasp_axis.py). A handle is part of the
cabinet, not a picked-up object, and recorded drawer episodes carry no axis label, so the handle's period is 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.state import StateView
from sim.tasks.drawer import CABINET, SLIDE
from sim.tasks.pick_place import footprint_period, grasp_yaw

HANDLE = f"{CABINET}/handle_site"
INSIDE = f"{CABINET}/inside"  # the drawer's cavity, a box site that slides with it
DRAWERS = ("drawer_open", "drawer_close", "drawer_put")
STOWS = ("drawer_stow",)  # the families that put an object into an open drawer as their first grasp
# the families that carry an object from a grasp to a release: the params naming it and where it goes
CARRIES = {"pick_place": ("target", "bin"), "stack": ("top", "bottom")}
FAMILIES = tuple(CARRIES) + DRAWERS + STOWS


@dataclass(frozen=True)
class Anchors:
    grasp: np.ndarray  # (3,) world point the grasp offset is measured from
    release: np.ndarray  # (3,) world point the release offset is measured from
    frame: np.ndarray  # (3, 3) rotation world <- anchor frame: offsets are in this frame
    yaw: float  # the grasp's yaw (fingers close along it)
    period: float  # the grasped thing's footprint period (0: round, or no axis to label)
    carried: str | None = None  # the body carried from grasp to release (datagen/views_carry.py); None: a handle

    def points(self, offsets: dict) -> tuple[np.ndarray, np.ndarray]:
        """The grasp and release points for `offsets` ({"grasp", "release"} in the anchor frame)."""
        return self.grasp + self.frame @ offsets["grasp"], self.release + self.frame @ offsets["release"]


def _object_pair(ep, picked: str, goal: str) -> Anchors:
    state = StateView(ep.world)
    name = ep.instance.params[picked]
    obj = ep.instance.obj(name)
    return Anchors(state.position(name), state.position(ep.instance.params[goal]), np.eye(3),
                   float(grasp_yaw(obj, state.rotation(name))), float(footprint_period(obj) or 0.0), name)


def drop_point(ep) -> np.ndarray:
    """The middle of the open drawer's floor, where the collector's place aims (give or take its sampling)."""
    lo, hi = StateView(ep.world).aabb(INSIDE)
    return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])


def object_to_drawer(ep) -> Anchors:
    """The named object (params "target") where it lies, and the open drawer's floor, in the cabinet's frame."""
    state = StateView(ep.world)
    name = ep.instance.params["target"]
    obj = ep.instance.obj(name)
    return Anchors(state.position(name), drop_point(ep), state.rotation(CABINET),
                   float(grasp_yaw(obj, state.rotation(name))), float(footprint_period(obj) or 0.0), name)


def _drawer(ep) -> Anchors:
    state = StateView(ep.world)
    frame = state.rotation(CABINET)
    axis = frame @ np.array([0.0, -1.0, 0.0])  # the direction the drawer opens (sim.tasks.drawer.move_drawer)
    handle = state.position(HANDLE)
    shut = handle - axis * (state.joint_value(SLIDE) - state.joint_range(SLIDE)[0])
    return Anchors(handle, shut, frame, float(np.arctan2(axis[1], axis[0])), 0.0)


def check_carries(task: str) -> None:
    """Refuse carrying views (datagen/views_carry.py) of a family that carries no object to a release."""
    if task not in CARRIES:
        raise ValueError(f"carrying views are of an object carried to its release ({', '.join(CARRIES)}), "
                         f"not of {task}, whose grasp is a handle")


def anchors(ep) -> Anchors:
    """The anchors of a built episode's scene (sim.build.build_episode), as it is before anything moves."""
    family = ep.instance.family
    if family in CARRIES:
        return _object_pair(ep, *CARRIES[family])
    if family in DRAWERS:
        return _drawer(ep)
    if family in STOWS:
        return object_to_drawer(ep)
    raise ValueError(f"no view labels for task family {family!r}; views know {', '.join(FAMILIES)}")
