"""Task objects built from parameters: blocks, cylinders, balls, bins, a drawer cabinet and a box with a hinged lid.

Each builder adds one body tree to the scene's worldbody and returns the top body. Names are the contract
with tasks and success predicates: the top body is `name`; a drawer's sliding part is `{name}/drawer` on the
joint `{name}/slide`; a lid is `{name}/lid` on the hinge `{name}/hinge`.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

# Walls and fixed furniture collide with everything; contype/conaffinity 1 is MuJoCo's default.
_STATIC_FRICTION = [0.8, 0.005, 0.0001]
_OBJECT_FRICTION = [0.9, 0.005, 0.0001]


@dataclass(frozen=True)
class Placement:
    """Where an object stands on the table: x, y of its base centre and its yaw (rad)."""

    x: float
    y: float
    yaw: float = 0.0

    def quat(self) -> list[float]:
        return [float(np.cos(self.yaw / 2)), 0.0, 0.0, float(np.sin(self.yaw / 2))]


def _material(spec: mujoco.MjSpec, name: str, rgba) -> str:
    spec.add_material(name=name, rgba=list(rgba))
    return name


def add_block(spec, name: str, half_size, rgba, at: Placement, mass: float = 0.08) -> mujoco.MjsBody:
    """A free-floating box resting on the table (z = 0 is the table top)."""
    body = spec.worldbody.add_body(name=name, pos=[at.x, at.y, half_size[2] + 1e-4], quat=at.quat())
    body.add_freejoint(name=f"{name}/free")
    body.add_geom(name=f"{name}/geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half_size), mass=mass,
                  material=_material(spec, f"{name}/mat", rgba), friction=_OBJECT_FRICTION, condim=4)
    return body


def add_cylinder(spec, name: str, radius: float, half_height: float, rgba, at: Placement,
                 mass: float = 0.08) -> mujoco.MjsBody:
    body = spec.worldbody.add_body(name=name, pos=[at.x, at.y, half_height + 1e-4], quat=at.quat())
    body.add_freejoint(name=f"{name}/free")
    body.add_geom(name=f"{name}/geom", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[radius, half_height, 0],
                  mass=mass, material=_material(spec, f"{name}/mat", rgba), friction=_OBJECT_FRICTION, condim=4)
    return body


def add_sphere(spec, name: str, radius: float, rgba, at: Placement, mass: float = 0.08) -> mujoco.MjsBody:
    """A free-floating ball resting on the table."""
    body = spec.worldbody.add_body(name=name, pos=[at.x, at.y, radius + 1e-4], quat=at.quat())
    body.add_freejoint(name=f"{name}/free")
    body.add_geom(name=f"{name}/geom", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0], mass=mass,
                  material=_material(spec, f"{name}/mat", rgba), friction=_OBJECT_FRICTION, condim=4)
    return body


def _add_open_box(body, name: str, inner_half, wall: float, material: str, z0: float = 0.0) -> None:
    """Floor and four walls of an open-top box whose inside spans ±inner_half (x, y) and 2·inner_half[2] high."""
    hx, hy, hz = inner_half
    box = mujoco.mjtGeom.mjGEOM_BOX
    common = dict(type=box, material=material, friction=_STATIC_FRICTION)
    body.add_geom(name=f"{name}/floor", size=[hx + wall, hy + wall, wall / 2], pos=[0, 0, z0 + wall / 2], **common)
    zc = z0 + wall + hz
    body.add_geom(name=f"{name}/wall_xp", size=[wall / 2, hy + wall, hz], pos=[hx + wall / 2, 0, zc], **common)
    body.add_geom(name=f"{name}/wall_xn", size=[wall / 2, hy + wall, hz], pos=[-hx - wall / 2, 0, zc], **common)
    body.add_geom(name=f"{name}/wall_yp", size=[hx, wall / 2, hz], pos=[0, hy + wall / 2, zc], **common)
    body.add_geom(name=f"{name}/wall_yn", size=[hx, wall / 2, hz], pos=[0, -hy - wall / 2, zc], **common)


def add_bin(spec, name: str, inner_half, rgba, at: Placement, wall: float = 0.008) -> mujoco.MjsBody:
    """A static open bin; `inner_half` is the half-extent of its inside (x, y, wall height / 2)."""
    body = spec.worldbody.add_body(name=name, pos=[at.x, at.y, 0.0], quat=at.quat())
    _add_open_box(body, name, inner_half, wall, _material(spec, f"{name}/mat", rgba))
    # The inside volume, for "inside" checks: a site the size of the cavity (invisible, no collision).
    body.add_site(name=f"{name}/inside", type=mujoco.mjtGeom.mjGEOM_BOX, group=5,
                  size=list(inner_half), pos=[0, 0, wall + inner_half[2]])
    return body


def add_drawer_cabinet(spec, name: str, at: Placement, rgba, handle_rgba=(0.2, 0.2, 0.2, 1.0),
                       inner_half=(0.09, 0.11, 0.045), travel: float = 0.16, height: float = 0.02,
                       damping: float = 2.0) -> mujoco.MjsBody:
    """A cabinet with one drawer sliding along the cabinet's -y axis (towards the robot when yaw = 0).

    The drawer joint `{name}/slide` is 0 when closed and `travel` when fully open.
    """
    hx, hy, hz = inner_half
    wall = 0.01
    mat = _material(spec, f"{name}/mat", rgba)
    box = mujoco.mjtGeom.mjGEOM_BOX
    cab = spec.worldbody.add_body(name=name, pos=[at.x, at.y, height], quat=at.quat())
    # Carcass: a box open on the -y side, slightly larger than the drawer.
    gx, gy, gz = hx + 0.01, hy + 0.004, hz + 0.01  # 4 mm side clearance around the drawer
    common = dict(type=box, material=mat, friction=_STATIC_FRICTION)
    cab.add_geom(name=f"{name}/bottom", size=[gx + wall, gy + wall / 2, wall / 2], pos=[0, wall / 2, wall / 2], **common)
    cab.add_geom(name=f"{name}/top", size=[gx + wall, gy + wall / 2, wall / 2], pos=[0, wall / 2, 2 * gz + 1.5 * wall], **common)
    cab.add_geom(name=f"{name}/back", size=[gx + wall, wall / 2, gz], pos=[0, gy + wall, gz + wall], **common)
    for sign, tag in ((1, "xp"), (-1, "xn")):
        cab.add_geom(name=f"{name}/side_{tag}", size=[wall / 2, gy + wall / 2, gz], pos=[sign * (gx + wall / 2), wall / 2, gz + wall], **common)
    # Legs lift the cabinet so the gripper can reach under the handle.
    cab.add_geom(name=f"{name}/plinth", size=[gx + wall, gy + wall, height / 2], pos=[0, wall / 2, -height / 2], **common)

    drawer = cab.add_body(name=f"{name}/drawer", pos=[0, 0, wall + 0.002])
    drawer.add_joint(name=f"{name}/slide", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, -1, 0],
                     range=[0.0, travel], damping=damping, armature=0.01, frictionloss=0.3)
    # The drawer runs on its slide joint, as on rails: it never rubs on its own carcass. (MuJoCo's
    # parent-child filter does not apply here because the carcass is welded to the world.)
    spec.add_exclude(bodyname1=name, bodyname2=f"{name}/drawer")
    dmat = _material(spec, f"{name}/drawer_mat", np.clip(np.asarray(rgba) * 0.85, 0, 1).tolist()[:3] + [1.0])
    _add_open_box(drawer, f"{name}/drawer", (hx, hy, hz * 0.8), 0.006, dmat)
    drawer.add_geom(name=f"{name}/front", type=box, size=[gx + wall * 0.8, 0.006, gz], pos=[0, -hy - 0.012, gz],
                    material=dmat, friction=_STATIC_FRICTION)
    # A bar handle the 2F-85 can close around from above.
    hmat = _material(spec, f"{name}/handle_mat", handle_rgba)
    # It stands 5 cm off the front, near its top edge, so a half-open gripper closes around it from above
    # without its wide housing touching the front.
    handle_y = -hy - 0.068
    handle_z = 2 * gz - 0.012
    drawer.add_geom(name=f"{name}/handle", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.008, 0.05, 0],
                    pos=[0, handle_y, handle_z], quat=[0.7071068, 0, 0.7071068, 0], material=hmat,
                    friction=[1.0, 0.005, 0.0001])
    for sign, tag in ((1, "r"), (-1, "l")):
        drawer.add_geom(name=f"{name}/handle_post_{tag}", type=box, size=[0.005, 0.026, 0.005],
                        pos=[sign * 0.045, handle_y + 0.026, handle_z], material=hmat)
    drawer.add_site(name=f"{name}/handle_site", pos=[0, handle_y, handle_z], group=5, size=[0.005, 0, 0])
    drawer.add_site(name=f"{name}/inside", type=box, group=5, size=[hx, hy, hz * 0.8], pos=[0, 0, 0.006 + hz * 0.8])
    return cab


def add_lid_box(spec, name: str, at: Placement, rgba, inner_half=(0.06, 0.06, 0.03)) -> mujoco.MjsBody:
    """An open box with a lid on a hinge along its +y edge; `{name}/hinge` is 0 closed, 1.5 rad (upright) open."""
    hx, hy, hz = inner_half
    wall = 0.006
    mat = _material(spec, f"{name}/mat", rgba)
    body = spec.worldbody.add_body(name=name, pos=[at.x, at.y, 0.0], quat=at.quat())
    _add_open_box(body, name, inner_half, wall, mat)
    top = wall + 2 * hz
    lid = body.add_body(name=f"{name}/lid", pos=[0, hy + wall, top])
    lid.add_joint(name=f"{name}/hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[-1, 0, 0], range=[0.0, 1.5],
                  damping=0.05, armature=0.002)
    lid.add_geom(name=f"{name}/lid_plate", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx + wall, hy + wall, wall / 2],
                 pos=[0, -hy - wall, wall / 2], material=mat, mass=0.05)
    # A bar handle standing 4.5 cm off the lid's front edge, like the drawer's, for a top-down grasp.
    front = -2 * hy - 2 * wall
    lid.add_geom(name=f"{name}/lid_handle", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.007, 0.035, 0],
                 pos=[0, front - 0.045, wall / 2], quat=[0.7071068, 0, 0.7071068, 0], material=mat, mass=0.005)
    for sign, tag in ((1, "r"), (-1, "l")):
        lid.add_geom(name=f"{name}/lid_post_{tag}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.004, 0.0225, 0.004],
                     pos=[sign * 0.03, front - 0.0225, wall / 2], material=mat, mass=0.002)
    body.add_site(name=f"{name}/inside", type=mujoco.mjtGeom.mjGEOM_BOX, group=5, size=list(inner_half),
                  pos=[0, 0, wall + hz])
    return body
