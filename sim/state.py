"""A read-only view of sim state for success predicates: poses, joints, contacts, bounding boxes.

This is the vocabulary success checks are written in, by hand in `sim/tasks/` and by a language model in
datagen's sandbox: `inside`, `on_top`, `in_contact`, `holding`, `joint_fraction`. Thresholds follow
"Scaling Up and Distilling Down": inside = bounding-box overlap > 25 % of the object's box; a joint within
20 % of a limit counts as at that limit.
"""

from __future__ import annotations

import mujoco
import numpy as np

from sim.robot import GRIPPER_PAD_GEOMS, GRIPPER_PREFIX

INSIDE_MIN_OVERLAP = 0.25
ON_TOP_MIN_NORMAL_Z = 0.9


class StateView:
    """Queries over one World's current state; it never changes the world."""

    def __init__(self, world):
        self._m = world.model
        self._d = world.data
        self._pad_geoms = {self._m.geom(n).id for n in GRIPPER_PAD_GEOMS}

    # -- poses and joints ---------------------------------------------------------------------------
    def _body(self, name: str) -> int:
        try:
            return self._m.body(name).id
        except KeyError:
            raise KeyError(f"no body named {name!r}; objects in this scene: {self.object_names()}") from None

    def object_names(self) -> list[str]:
        """Top-level bodies other than the robot: the task's objects and furniture."""
        names = []
        for i in range(1, self._m.nbody):
            if self._m.body_parentid[i] == 0 and self._m.body(i).name != "base":
                names.append(self._m.body(i).name)
        return names

    def position(self, name: str) -> np.ndarray:
        """World position of a body, or of a named geom or site (e.g. "table")."""
        for kind, xpos in ((mujoco.mjtObj.mjOBJ_GEOM, self._d.geom_xpos), (mujoco.mjtObj.mjOBJ_SITE, self._d.site_xpos)):
            if mujoco.mj_name2id(self._m, mujoco.mjtObj.mjOBJ_BODY, name) < 0:
                i = mujoco.mj_name2id(self._m, kind, name)
                if i >= 0:
                    return xpos[i].copy()
        return self._d.xpos[self._body(name)].copy()

    def rotation(self, body: str) -> np.ndarray:
        return self._d.xmat[self._body(body)].reshape(3, 3).copy()

    def velocity(self, body: str) -> np.ndarray:
        """Linear velocity (world frame) of the body's origin."""
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self._m, self._d, mujoco.mjtObj.mjOBJ_BODY, self._body(body), vel, 0)
        return vel[3:].copy()

    def joint_value(self, joint: str) -> float:
        return float(self._d.qpos[self._m.jnt_qposadr[self._m.joint(joint).id]])

    def joint_range(self, joint: str) -> tuple[float, float]:
        lo, hi = self._m.jnt_range[self._m.joint(joint).id]
        return float(lo), float(hi)

    def joint_fraction(self, joint: str) -> float:
        """Where a joint sits in its range: 0 at the lower limit, 1 at the upper."""
        lo, hi = self.joint_range(joint)
        return (self.joint_value(joint) - lo) / (hi - lo)

    def tcp_position(self) -> np.ndarray:
        return self._d.site_xpos[self._m.site("tcp").id].copy()

    # -- boxes -------------------------------------------------------------------------------------------
    def aabb(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World-aligned bounding box of a body's own geoms, or of a box site named `name`."""
        if mujoco.mj_name2id(self._m, mujoco.mjtObj.mjOBJ_SITE, name) >= 0:
            sid = self._m.site(name).id
            return _box_aabb(self._d.site_xpos[sid], self._d.site_xmat[sid], self._m.site_size[sid])
        bid = self._body(name)
        lows, highs = [], []
        for g in np.flatnonzero(self._m.geom_bodyid == bid):
            lo, hi = _geom_aabb(self._m, self._d, g)
            lows.append(lo)
            highs.append(hi)
        if not lows:
            raise KeyError(f"body {name!r} has no geoms to bound")
        return np.min(lows, axis=0), np.max(highs, axis=0)

    def overlap_fraction(self, obj: str, region: str) -> float:
        """Fraction of `obj`'s bounding box volume that lies in `region`'s bounding box."""
        (alo, ahi), (blo, bhi) = self.aabb(obj), self.aabb(region)
        inter = np.clip(np.minimum(ahi, bhi) - np.maximum(alo, blo), 0.0, None)
        vol = float(np.prod(ahi - alo))
        return float(np.prod(inter)) / vol if vol > 0 else 0.0

    def inside(self, obj: str, container: str, min_overlap: float = INSIDE_MIN_OVERLAP) -> bool:
        """`obj` is inside `container` (its `{container}/inside` cavity when it has one)."""
        cavity = f"{container}/inside"
        region = cavity if mujoco.mj_name2id(self._m, mujoco.mjtObj.mjOBJ_SITE, cavity) >= 0 else container
        return self.overlap_fraction(obj, region) > min_overlap

    # -- contacts ----------------------------------------------------------------------------------------
    def _root_of(self, body_id: int) -> int:
        while self._m.body_parentid[body_id] != 0:
            body_id = self._m.body_parentid[body_id]
        return body_id

    def _matches(self, geom: int, name: str) -> bool:
        """A geom belongs to `name` if its body is `name` or `name`'s subtree ("robot" = arm + gripper)."""
        body = self._m.geom_bodyid[geom]
        if name == "robot":
            return self._m.body(self._root_of(body)).name == "base"
        if name in ("table", "floor"):
            return self._m.geom(geom).name == name
        target = self._body(name)
        while body != 0:
            if body == target:
                return True
            body = self._m.body_parentid[body]
        return False

    def contacts(self, a: str, b: str):
        """(normal pointing from a to b, force magnitude) of each contact between a and b."""
        out = []
        force = np.zeros(6)
        for i in range(self._d.ncon):
            c = self._d.contact[i]
            g1, g2 = c.geom1, c.geom2
            if self._matches(g1, a) and self._matches(g2, b):
                sign = 1.0
            elif self._matches(g2, a) and self._matches(g1, b):
                sign = -1.0
            else:
                continue
            mujoco.mj_contactForce(self._m, self._d, i, force)
            out.append((sign * c.frame[:3].copy(), float(abs(force[0]))))
        return out

    def in_contact(self, a: str, b: str) -> bool:
        return bool(self.contacts(a, b))

    def on_top(self, upper: str, lower: str) -> bool:
        """`upper` rests on `lower`: they touch through a roughly horizontal face and upper is above."""
        if self.position(upper)[2] <= self.position(lower)[2]:
            return False
        return any(-n[2] >= ON_TOP_MIN_NORMAL_Z or n[2] >= ON_TOP_MIN_NORMAL_Z for n, _ in self.contacts(upper, lower))

    def holding(self, obj: str) -> bool:
        """Both finger pads touch `obj` (the gripper holds it)."""
        sides = set()
        for i in range(self._d.ncon):
            c = self._d.contact[i]
            for pad, other in ((c.geom1, c.geom2), (c.geom2, c.geom1)):
                if pad in self._pad_geoms and self._matches(other, obj):
                    sides.add("left" if "left" in self._m.geom(pad).name else "right")
        return len(sides) == 2

    def touching_robot(self, obj: str) -> bool:
        return self.in_contact(obj, "robot")


def _box_aabb(pos, xmat, half) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(xmat).reshape(3, 3)
    ext = np.abs(R) @ np.asarray(half[:3])
    return pos - ext, pos + ext


def _geom_aabb(m, d, g) -> tuple[np.ndarray, np.ndarray]:
    """Tight world box of a primitive geom from its local AABB (MuJoCo stores center + half sizes)."""
    local = m.geom_aabb[g]  # (center xyz, half xyz) in the geom frame
    R = d.geom_xmat[g].reshape(3, 3)
    centre = d.geom_xpos[g] + R @ local[:3]
    ext = np.abs(R) @ local[3:]
    return centre - ext, centre + ext


__all__ = ["StateView", "INSIDE_MIN_OVERLAP", "GRIPPER_PREFIX"]
