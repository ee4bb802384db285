"""Collision checking of arm configurations on a scratch copy of the world (the live one is never touched).

Why a model copy and not just a data copy: the copy's contype/conaffinity bits are rewritten so MuJoCo's
broadphase only produces the contacts planning cares about, which keeps a check at tens of microseconds:

    geoms          contype  conaffinity   collide with
    environment    1        0             arm, gripper, held object (never each other: resting objects and
                                          the drawer on its rails are physics' business)
    arm            2        1|2|4|8       everything (adjacent links are filtered by MuJoCo's parent rule)
    gripper        4        1             environment and arm (not itself: its linkage touches by design)
    held object    8        1             environment and arm (not the gripper that holds it)

A geom margin lets callers ask for clearance (contacts closer than `clearance` count). A held object (name
+ pose relative to the TCP + the gripper's joint angles around it) is moved with the TCP before checking.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import mujoco
import numpy as np

from sim.robot import GRIPPER_PREFIX

ENV, ARM, GRIP, HELD = 1, 2, 4, 8
_OPENINGS = np.linspace(0.0, 1.0, 5)
_GRIPPER_TABLE: dict[str, np.ndarray] = {}  # variant -> (5, n_gripper_joints) joint angles at _OPENINGS


@dataclass(frozen=True)
class Workspace:
    """Where the runtime's safety filter lets the TCP go: a box, and finger points above the table.

    Demonstrations the real robot's filter would clip teach a policy moves it cannot make, so data
    generation keeps to the same region (shrunk by the filter's target margin).
    """

    box_min: np.ndarray
    box_max: np.ndarray
    floor: float  # z the finger points must stay above
    points: np.ndarray  # (k, 3) finger points in the TCP frame

    def slack(self, pos, R) -> float:
        """Smallest distance inside the region (negative: outside)."""
        z = pos[2] + self.points @ R[2] if len(self.points) else np.array([np.inf])
        return float(min(np.min(pos - self.box_min), np.min(self.box_max - pos), np.min(z) - self.floor))


def safety_workspace(variant: str) -> Workspace | None:
    """The safety layer's default workspace for `variant`, or None when safety.limits is not available."""
    try:
        from safety.limits import default_limits
    except ImportError:
        return None
    w = default_limits(variant).workspace
    m = float(w.target_margin)
    return Workspace(np.asarray(w.box_min, float) + m, np.asarray(w.box_max, float) - m,
                     float(w.table_z + w.finger_clearance + m), np.asarray(w.gripper_points, float).reshape(-1, 3))


@dataclass
class Held:
    """An object in the gripper: its pose in the TCP frame and the gripper joint angles holding it."""

    body: str
    T_tcp_obj: np.ndarray
    gripper_qpos: np.ndarray | None = None


class CollisionChecker:
    """`is_free(q, ...)` for the arm of `world`, against the world's object poses at the last `sync()`."""

    def __init__(self, world, margin: float = 0.02, workspace: Workspace | None = None):
        self.world = world
        self.workspace = workspace  # None: no region check (e.g. tests of pure collision)
        m = self.model = copy.deepcopy(world.model)
        self.data = mujoco.MjData(m)
        self.margin = float(margin)
        root = world.model.body("base").id
        bodies = np.arange(m.nbody)
        robot_body = np.array([_root(m, b) == root for b in bodies])
        collidable = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        body_of = m.geom_bodyid
        is_grip = np.array([m.body(b).name.startswith(GRIPPER_PREFIX) for b in body_of])
        self.robot_geoms = collidable & robot_body[body_of]
        self.gripper_geoms = self.robot_geoms & is_grip
        arm = self.robot_geoms & ~is_grip
        env = collidable & ~self.robot_geoms
        m.geom_contype[:] = 0
        m.geom_conaffinity[:] = 0
        m.geom_contype[env], m.geom_conaffinity[env] = ENV, 0
        m.geom_contype[arm], m.geom_conaffinity[arm] = ARM, ENV | ARM | GRIP | HELD
        m.geom_contype[self.gripper_geoms], m.geom_conaffinity[self.gripper_geoms] = GRIP, ENV
        # The first link only turns about the vertical axis: its distance to the table never changes (3 mm).
        first = np.array([m.body_parentid[b] == root for b in body_of]) & arm
        m.geom_conaffinity[first] = ARM | GRIP | HELD
        m.geom_margin[collidable] = self.margin
        self._env = env
        _refresh_bodies(m)
        self.arm_adr = world.arm_qpos_adr
        gj = [j for j in range(m.njnt) if m.joint(j).name.startswith(GRIPPER_PREFIX)]
        self.gripper_adr = np.array([m.jnt_qposadr[j] for j in gj])
        self.tcp_site = world.tcp_site
        self._held_body = -1  # body whose geoms carry the HELD bits now
        self._allow_cache: dict = {}
        self._table = gripper_table(world, self.gripper_adr)
        self.sync()

    # -- state -------------------------------------------------------------------------------------------
    def sync(self) -> None:
        """Take object, drawer and gripper positions from the live world (call when planning starts)."""
        self._qpos0 = self.world.data.qpos.copy()
        self.data.qpos[:] = self._qpos0
        self.data.qvel[:] = 0.0

    def gripper_qpos(self, opening) -> np.ndarray:
        """Gripper joint angles for a command in [0, 1] (0 open), or the live angles for None."""
        if opening is None:
            return self._qpos0[self.gripper_adr].copy()
        opening = np.asarray(opening, dtype=float)
        if opening.ndim:  # explicit joint angles, e.g. closed around an object
            return opening
        return np.array([np.interp(float(opening), _OPENINGS, col) for col in self._table.T])

    def body_geoms(self, name: str) -> np.ndarray:
        """Boolean geom mask for a body's subtree ("robot" = arm + gripper), or for one geom by name."""
        m = self.model
        if name == "robot":
            return self.robot_geoms.copy()
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid > 0:
            sub = np.array([_is_descendant(m, b, bid) for b in range(m.nbody)])
            return sub[m.geom_bodyid]
        gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
        if gid < 0:
            raise KeyError(f"no body or geom named {name!r}")
        mask = np.zeros(m.ngeom, bool)
        mask[gid] = True
        return mask

    def _allowed(self, allow) -> np.ndarray | None:
        """(ngeom, ngeom) mask of allowed contact pairs: a name allows all its contacts, a pair only those."""
        key = tuple(allow)
        if not key:
            return None
        if key not in self._allow_cache:
            n = self.model.ngeom
            A = np.zeros((n, n), bool)
            for item in key:
                if isinstance(item, str):
                    g = self.body_geoms(item)
                    A[g, :] = True
                    A[:, g] = True
                else:
                    a, b = self.body_geoms(item[0]), self.body_geoms(item[1])
                    A |= np.outer(a, b) | np.outer(b, a)
            self._allow_cache[key] = A
        return self._allow_cache[key]

    def _set_held(self, held: Held | None) -> None:
        m = self.model
        bid = -1 if held is None else m.body(held.body).id
        if bid == self._held_body:
            return
        if self._held_body >= 0:  # back to an ordinary environment object, at its synced pose
            g = m.geom_bodyid == self._held_body
            m.geom_contype[g & self._env], m.geom_conaffinity[g & self._env] = ENV, 0
            adr = m.jnt_qposadr[m.body_jntadr[self._held_body]]
            self.data.qpos[adr:adr + 7] = self._qpos0[adr:adr + 7]
        if bid >= 0:
            g = (m.geom_bodyid == bid) & self._env
            m.geom_contype[g], m.geom_conaffinity[g] = HELD, ENV
        self._held_body = bid
        _refresh_bodies(m)

    # -- queries -----------------------------------------------------------------------------------------
    def _collide(self, q, held, gripper) -> None:
        m, d = self.model, self.data
        self._set_held(held)
        d.qpos[self.arm_adr] = q
        if held is not None and held.gripper_qpos is not None and gripper is None:
            gripper = held.gripper_qpos
        d.qpos[self.gripper_adr] = self.gripper_qpos(gripper)
        mujoco.mj_kinematics(m, d)
        if held is not None:
            T = np.eye(4)
            T[:3, :3] = d.site_xmat[self.tcp_site].reshape(3, 3)
            T[:3, 3] = d.site_xpos[self.tcp_site]
            T = T @ held.T_tcp_obj
            adr = m.jnt_qposadr[m.body_jntadr[self._held_body]]
            d.qpos[adr:adr + 3] = T[:3, 3]
            mujoco.mju_mat2Quat(d.qpos[adr + 3:adr + 7], T[:3, :3].flatten())
            mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        if self.workspace is not None:
            self._slack = self.workspace.slack(d.site_xpos[self.tcp_site], d.site_xmat[self.tcp_site].reshape(3, 3))

    def _hits(self, allow, clearance) -> np.ndarray:
        d = self.data
        n = d.ncon
        if n == 0:
            return np.zeros(0, int)
        c = d.contact
        bad = c.dist[:n] < clearance
        A = self._allowed(allow)
        if A is not None:
            bad &= ~A[c.geom1[:n], c.geom2[:n]]
        return np.flatnonzero(bad)

    def is_free(self, q, held: Held | None = None, gripper=None, allow=(), clearance: float = 0.0) -> bool:
        """No contact closer than `clearance` (m; negative tolerates penetration) except `allow`ed ones.

        `gripper`: None = the held object's grasp angles or else the live gripper; a float opening in [0, 1];
        or explicit joint angles. `allow`: names (all their contacts) or (name, name) pairs.
        """
        if clearance > self.margin:
            raise ValueError(f"clearance {clearance} exceeds the checker's margin {self.margin}")
        self._collide(q, held, gripper)
        if self.workspace is not None and self._slack < 0.0:
            return False
        return len(self._hits(allow, clearance)) == 0

    def collisions(self, q, held: Held | None = None, gripper=None, allow=(), clearance: float = 0.0):
        """The offending contacts as (geom1 name, geom2 name, distance), for messages and tests."""
        self._collide(q, held, gripper)
        m, c = self.model, self.data.contact
        out = [(_geom_label(m, c.geom1[i]), _geom_label(m, c.geom2[i]), float(c.dist[i]))
               for i in self._hits(allow, clearance)]
        if self.workspace is not None and self._slack < 0.0:
            out.append(("tcp", "workspace", self._slack))
        return out

    def path_free(self, Q, **kw) -> int:
        """Index of the first colliding configuration in Q (rows), or -1 when all are free."""
        for i, q in enumerate(np.atleast_2d(Q)):
            if not self.is_free(q, **kw):
                return i
        return -1


def _refresh_bodies(m) -> None:
    """MuJoCo's broadphase filters bodies by the OR of their geoms' bits and the max margin (compiled once)."""
    m.body_contype[:] = 0
    m.body_conaffinity[:] = 0
    m.body_margin[:] = 0.0
    for g in range(m.ngeom):
        b = m.geom_bodyid[g]
        m.body_contype[b] |= m.geom_contype[g]
        m.body_conaffinity[b] |= m.geom_conaffinity[g]
        m.body_margin[b] = max(m.body_margin[b], m.geom_margin[g])


def _root(m, b: int) -> int:
    while m.body_parentid[b] != 0:
        b = m.body_parentid[b]
    return b


def _is_descendant(m, b: int, ancestor: int) -> bool:
    while b != 0:
        if b == ancestor:
            return True
        b = m.body_parentid[b]
    return False


def _geom_label(m, g: int) -> str:
    return m.geom(g).name or f"{m.body(m.geom_bodyid[g]).name}#{g}"


def gripper_table(world, adr: np.ndarray) -> np.ndarray:
    """Gripper joint angles at a few openings, found once per variant by closing it with contacts off."""
    key = world.variant.name
    if key not in _GRIPPER_TABLE:
        m = copy.deepcopy(world.model)
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        rows = []
        for opening in _OPENINGS:
            d = mujoco.MjData(m)
            d.qpos[:] = world.data.qpos
            d.ctrl[:] = world.data.ctrl
            d.ctrl[world.gripper_actuator] = opening * 255.0
            mujoco.mj_step(m, d, nstep=300)
            rows.append(d.qpos[adr].copy())
        _GRIPPER_TABLE[key] = np.array(rows)
    return _GRIPPER_TABLE[key]
