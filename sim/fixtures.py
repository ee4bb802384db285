"""The scene's fixed furniture as axis-aligned boxes, the form a cell's safety config gives its keep-out zones.

Why: a real cell's bins are fixtures that the integrator measures once and declares to the safety layer
(`workspace.keepout` in the limits file). The sim twin knows its fixtures exactly, so it can declare them
the same way: the finger points stay out of a bin's walls and the collision guard slows near them, where a
pad used to press on a wall until the contact force stopped the arm.

What counts: collision geoms of bodies welded to the world that are not the robot (the bins; a cabinet's
carcass but not its drawer, which slides). The table is the safety layer's table plane already, and the
room's walls and floor (world geoms) lie outside the TCP box.
"""

from __future__ import annotations

import mujoco
import numpy as np

from sim.robot import ARM_BODIES

Box = tuple[float, float, float, float, float, float]  # (xmin, ymin, zmin, xmax, ymax, zmax), base frame
OVERHANG = 0.005  # m: how far a turned geom's boxes may stand off its faces, per tilted axis
MAX_CUTS = 8  # pieces along one axis at most (a 0.28 m panel at the cabinet's 0.2 rad needs 6)


def fixture_boxes(model: mujoco.MjModel, data: mujoco.MjData) -> tuple[Box, ...]:
    """World-aligned bounding boxes of the fixtures' collision geoms at the current (forwarded) state."""
    robot_root = model.body(ARM_BODIES[0]).id
    out: list[Box] = []
    for g in range(model.ngeom):
        b = int(model.geom_bodyid[g])
        if b == 0 or model.body_weldid[b] != 0 or model.body_rootid[b] == robot_root:
            continue
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        R = data.geom_xmat[g].reshape(3, 3)
        c = data.geom_xpos[g] + R @ centre
        for pc, ph in _pieces(R, half):
            h = np.abs(R) @ ph  # the piece's extent along the world axes
            p = c + R @ pc
            out.append(tuple(float(x) for x in (*(p - h), *(p + h))))
    return tuple(out)


def _pieces(R: np.ndarray, half: np.ndarray):
    """(centre, half) pieces of a box, in its own frame: a grid cut along each of its axes that the turn tilts
    off the world's, so that every piece's world-aligned box stands at most about OVERHANG (per tilted axis) off
    the turned box. Why every axis: one box around a cabinet's side panel turned by 10 degrees is 5 cm thick and
    reaches into the drawer the arm has to put things in; one box around its top or bottom panel, flat and
    turned in yaw, reaches up to 4 cm in front of the drawer's face at 0.17 rad, right where the fingers come
    down to the handle: the guard held them there until the episode timed out (policy/EXPERIMENTS.md, "The
    cabinet's yaw extreme: more data there, and the guard's phantom overhang")."""
    counts = []
    for k in range(3):
        col = np.abs(R[:, k])
        lean = float(col.sum() - col.max())  # how far a unit along this axis reaches off its nearest world axis
        counts.append(min(MAX_CUTS, max(1, int(np.ceil(lean * half[k] / OVERHANG)))))
    ph = half / np.array(counts)
    for i in range(counts[0]):
        for j in range(counts[1]):
            for k in range(counts[2]):
                pc = -half + (2 * np.array([i, j, k]) + 1) * ph
                yield pc, ph.copy()


__all__ = ["Box", "fixture_boxes"]
