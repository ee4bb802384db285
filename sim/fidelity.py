"""Rendering fidelity levels: the robot's visual geometry and the renderer's settings, traded for speed.

`full` keeps the Menagerie meshes (UR5e .obj, ~360k vertices; 2F-85 .stl) and MuJoCo's default render quality
(shadow maps, 4x multisampling). `fast` draws the robot with a few dozen primitives (cylinders for the UR5e's
joint housings, blue caps and link tubes; boxes for the gripper housing, linkages and pads) and renders without
shadows or multisampling. On llvmpipe (software GL) those are what cost: every mesh vertex goes through the
vertex pipeline once per pass, each shadow-casting light adds two passes (one into a `shadowsize`² depth map),
and multisampling multiplies the fill and resolve work.

Physics is identical at both levels: only visual geoms (contype = conaffinity = 0, group 2) change. Collision
geoms, bodies, joints, actuators and inertias stay as they are; a body whose inertia MuJoCo would infer from a
replaced visual mesh (the 2F-85's base mount and silicone pads) gets that inertia made explicit first.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sim.robot import GRIPPER_PREFIX

FIDELITY_LEVELS = ("full", "fast")
FIDELITY_TEXT = "sudd/fidelity"  # a model text element naming the level, for CameraRenderer's defaults
DEFAULT_LEVEL = "full"


@dataclass(frozen=True)
class RenderSettings:
    """How a level renders. `None` quality fields leave the model's own value (MuJoCo's defaults)."""

    shadows: bool
    offsamples: int | None = None  # multisampling of the offscreen buffer (MuJoCo default 4)
    shadowsize: int | None = None  # shadow-map side in texels (MuJoCo default 4096)
    numslices: int | None = None  # primitive tessellation (MuJoCo default 28 slices, 16 stacks)
    numstacks: int | None = None


_RENDER_SETTINGS = {
    "full": RenderSettings(shadows=True),
    # Shadow maps dominate a software renderer's frame even at small sizes (two extra passes per light), so
    # `fast` turns them off; the map is kept small so that turning them back on stays affordable.
    "fast": RenderSettings(shadows=False, offsamples=0, shadowsize=1024, numslices=16, numstacks=8),
}


def check_level(level: str) -> str:
    if level not in FIDELITY_LEVELS:
        raise ValueError(f"unknown fidelity level {level!r}; expected one of {', '.join(FIDELITY_LEVELS)}")
    return level


def render_settings(level: str) -> RenderSettings:
    return _RENDER_SETTINGS[check_level(level)]


def model_fidelity(model: mujoco.MjModel) -> str:
    """The level a compiled model was built at (`full` when apply_fidelity never ran on its spec)."""
    tid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, FIDELITY_TEXT)
    if tid < 0:
        return DEFAULT_LEVEL
    adr, size = int(model.text_adr[tid]), int(model.text_size[tid])
    level = bytes(model.text_data[adr:adr + size]).rstrip(b"\0").decode()
    return level if level in FIDELITY_LEVELS else DEFAULT_LEVEL


def apply_fidelity(spec: mujoco.MjSpec, level: str) -> None:
    """Set a scene spec's visual fidelity before compiling it; `full` leaves it unchanged."""
    check_level(level)
    existing = _spec_level(spec)
    if existing is not None:
        if existing != level:
            raise ValueError(f"spec already set to fidelity {existing!r}; cannot change it to {level!r}")
        return
    if level == "full":
        return
    settings = render_settings(level)
    quality = spec.visual.quality
    for name in ("offsamples", "shadowsize", "numslices", "numstacks"):
        value = getattr(settings, name)
        if value is not None:
            setattr(quality, name, value)
    _simplify_robot(spec)
    spec.add_text(name=FIDELITY_TEXT, data=level)


def _spec_level(spec: mujoco.MjSpec) -> str | None:
    for text in spec.texts:
        if text.name == FIDELITY_TEXT:
            return text.data
    return None


# -- the fast robot -------------------------------------------------------------------------------------------
# Each entry: ("cyl", axis, radius, start, end, material[, (centre_a, centre_b)]) for a cylinder along a body
# axis ("x", "y" or "z") from `start` to `end`, centred on the other two coordinates (default 0, 0); or
# ("box", centre, half_sizes, material[, tilt_x]) for a box, optionally tilted about the body's x axis (rad).
# Dimensions come from the Menagerie meshes (their extents in each body frame); materials are the models' own.

_UR_BLACK, _UR_JOINT, _UR_LINK, _UR_BLUE = "black", "jointgray", "linkgray", "urblue"
_G_BLACK, _G_GRAY = GRIPPER_PREFIX + "black", GRIPPER_PREFIX + "gray"
_PAD_RGBA = (0.5, 0.5, 0.5, 1.0)  # the Menagerie pad mesh has no material: MuJoCo's default grey


def _housing(axis, r, lo, cap_split, cap_end, centre=(0.0, 0.0), ring=None):
    """A joint housing: grey cylinder from `lo` to `cap_split`, blue cap to `cap_end`, optional black ring."""
    parts = [("cyl", axis, r, lo, cap_split, _UR_JOINT, centre),
             ("cyl", axis, r + 0.002, cap_split, cap_end, _UR_BLUE, centre)]
    if ring is not None:
        parts.append(("cyl", axis, r - 0.0005, ring[0], ring[1], _UR_BLACK, centre))
    return parts


def _ur5e_parts() -> dict[str, list]:
    return {
        "base": [
            ("cyl", "z", 0.0755, 0.0, 0.085, _UR_JOINT),
            ("cyl", "z", 0.058, 0.085, 0.099, _UR_BLACK),
        ],
        "shoulder_link": [
            *_housing("z", 0.058, -0.064, 0.02, 0.0715),
            ("cyl", "y", 0.058, 0.0, 0.0602, _UR_JOINT),
            ("cyl", "y", 0.058, 0.0602, 0.0744, _UR_BLACK),
        ],
        "upper_arm_link": [
            *_housing("y", 0.058, -0.064, 0.02, 0.0718),  # shoulder end
            ("cyl", "z", 0.058, 0.058, 0.073, _UR_BLACK),
            ("cyl", "z", 0.052, 0.073, 0.095, _UR_LINK),
            ("cyl", "z", 0.045, 0.095, 0.329, _UR_LINK),
            ("cyl", "z", 0.052, 0.329, 0.351, _UR_LINK),
            ("cyl", "z", 0.058, 0.351, 0.364, _UR_BLACK),
            *_housing("y", 0.058, -0.064, 0.02, 0.0718, centre=(0.0, 0.425), ring=(-0.078, -0.064)),  # elbow
        ],
        "forearm_link": [
            ("cyl", "y", 0.058, -0.048, 0.053, _UR_JOINT),  # elbow housing
            ("cyl", "z", 0.048, 0.045, 0.0765, _UR_BLACK),
            ("cyl", "z", 0.044, 0.0765, 0.10, _UR_LINK),
            ("cyl", "z", 0.037, 0.10, 0.339, _UR_LINK),
            ("cyl", "z", 0.0375, 0.339, 0.346, _UR_BLACK),
            *_housing("y", 0.038, 0.046, -0.02, -0.0565, centre=(0.0, 0.392), ring=(0.046, 0.053)),  # wrist 1
        ],
        "wrist_1_link": [
            ("cyl", "y", 0.038, 0.053, 0.127, _UR_JOINT),
            *_housing("z", 0.038, 0.046, -0.02, -0.0563, centre=(0.0, 0.127), ring=(0.046, 0.0536)),  # wrist 2
        ],
        "wrist_2_link": [
            ("cyl", "z", 0.038, 0.0536, 0.0997, _UR_JOINT),
            *_housing("y", 0.038, 0.0456, -0.02, -0.0567, centre=(0.0, 0.0997), ring=(0.0456, 0.0531)),  # wrist 3
        ],
        "wrist_3_link": [
            ("cyl", "y", 0.0376, 0.0531, 0.0989, _UR_LINK),  # the tool flange
            ("box", (0.0, 0.0715, 0.038), (0.012, 0.009, 0.0055), _UR_LINK),  # its tool connector
        ],
    }


def _gripper_parts() -> dict[str, list]:
    p = GRIPPER_PREFIX
    finger = {
        "driver": [("box", (0.0, 0.0155, 0.001), (0.0075, 0.021, 0.0075), _G_GRAY)],
        "coupler": [("box", (0.0, 0.003, 0.0235), (0.0075, 0.005, 0.028), _G_BLACK, -0.125)],
        "spring_link": [("box", (0.0, 0.0185, 0.022), (0.017, 0.005, 0.031), _G_BLACK, -0.70)],
        "follower": [("box", (0.0, -0.009, 0.003), (0.0075, 0.0145, 0.008), _G_BLACK),
                     ("box", (0.0, -0.0154, 0.028), (0.007, 0.0035, 0.0165), _G_BLACK)],
        "pad": [("box", (0.0, -0.0025, 0.01875), (0.011, 0.0025, 0.01875), _PAD_RGBA)],
        "silicone_pad": [("box", (0.0, -0.0058, 0.01875), (0.011, 0.0008, 0.01875), _G_BLACK)],
    }
    parts = {
        p + "base_mount": [("cyl", "z", 0.0375, -0.007, 0.0069, _G_BLACK)],
        p + "base": [
            ("cyl", "z", 0.0375, -0.004, 0.043, _G_BLACK),
            ("box", (0.0, 0.0, 0.0548), (0.012, 0.0424, 0.0118), _G_BLACK),
            ("box", (0.0, 0.0, 0.078), (0.011, 0.029, 0.012), _G_BLACK),
        ],
    }
    for side in ("left", "right"):
        for link, geoms in finger.items():
            parts[f"{p}{side}_{link}"] = geoms
    return parts


_AXES = {"x": 0, "y": 1, "z": 2}


def _is_visual(geom: mujoco.MjsGeom) -> bool:
    return geom.contype == 0 and geom.conaffinity == 0 and geom.group == 2


def _set_part(spec: mujoco.MjSpec, geom: mujoco.MjsGeom, part) -> None:
    """Make `geom` (a new geom, or a visual mesh geom being reused) the primitive described by `part`."""
    kind = part[0]
    geom.contype, geom.conaffinity, geom.group = 0, 0, 2
    geom.meshname = ""
    geom.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    if kind == "cyl":
        _, axis, radius, start, end, look, *centre = part
        p0, p1 = np.zeros(3), np.zeros(3)
        others = [i for i in range(3) if i != _AXES[axis]]
        p0[others] = p1[others] = centre[0] if centre else (0.0, 0.0)
        p0[_AXES[axis]], p1[_AXES[axis]] = start, end
        geom.type = mujoco.mjtGeom.mjGEOM_CYLINDER
        geom.size = [radius, 0.0, 0.0]
        geom.fromto = [*p0, *p1]
    elif kind == "box":
        _, centre, half, look, *tilt = part
        angle = tilt[0] if tilt else 0.0
        geom.type = mujoco.mjtGeom.mjGEOM_BOX
        geom.size = list(half)
        geom.pos = list(centre)
        geom.quat = [float(np.cos(angle / 2)), float(np.sin(angle / 2)), 0.0, 0.0]
        geom.fromto = [np.nan] * 6
    else:  # pragma: no cover - a typo in the tables
        raise ValueError(f"unknown part kind {kind!r}")
    if isinstance(look, str) and spec.material(look) is not None:
        geom.material = look
    else:
        geom.material = ""
        geom.rgba = list(look) if not isinstance(look, str) else [0.2, 0.2, 0.2, 1.0]


def _simplify_robot(spec: mujoco.MjSpec) -> None:
    parts = {**_ur5e_parts(), **_gripper_parts()}
    todo = []
    for body_name, body_parts in parts.items():
        body = spec.body(body_name)
        if body is None:
            continue
        visual = [g for g in body.geoms if _is_visual(g) and g.type == mujoco.mjtGeom.mjGEOM_MESH]
        if visual:
            todo.append((body, visual, body_parts))
    # Bodies with an explicit inertial first: dropping their meshes makes the inertia inference below cheaper.
    todo.sort(key=lambda item: not item[0].explicitinertial)
    replaced: set[str] = set()
    for body, visual, body_parts in todo:
        if not body.explicitinertial:
            # MuJoCo would infer this body's inertia from its geoms, the visual meshes included: freeze it.
            _delete_unused_meshes(spec, replaced)
            _freeze_inertia(spec, body)
        replaced |= {g.meshname for g in visual}
        # Reuse the mesh geoms as primitives (deleting spec elements is slow), then add or drop the difference.
        for geom, part in zip(visual, body_parts):
            _set_part(spec, geom, part)
        for part in body_parts[len(visual):]:
            _set_part(spec, body.add_geom(), part)
        for geom in visual[len(body_parts):]:
            spec.delete(geom)
    _delete_unused_meshes(spec, replaced)


# Inertias inferred from geoms, by what they were inferred from: inferring one compiles the spec, so a
# process building many scenes pays for it once.
_INERTIA_CACHE: dict[tuple, tuple] = {}


def _inertia_key(spec: mujoco.MjSpec, body: mujoco.MjsBody) -> tuple:
    def vec(x):  # hashable and comparable, NaN (unset) included
        return tuple(None if np.isnan(v) else float(v) for v in np.atleast_1d(np.asarray(x, float)))

    geoms = []
    for g in body.geoms:
        mesh = spec.mesh(g.meshname) if g.type == mujoco.mjtGeom.mjGEOM_MESH else None
        mesh_key = None
        if mesh is not None:
            mesh_key = (mesh.file, vec(mesh.scale), int(mesh.inertia), vec(mesh.refpos), vec(mesh.refquat))
        alt = g.alt
        orientation = (int(alt.type), vec(alt.axisangle), vec(alt.euler), vec(alt.xyaxes), vec(alt.zaxis))
        geoms.append((int(g.type), mesh_key, vec(g.size), vec(g.pos), vec(g.quat), orientation, vec(g.fromto),
                      vec(g.density), vec(g.mass), int(g.group), int(g.typeinertia)))
    compiler = getattr(body, "compiler", None) or spec.compiler
    return (body.name, tuple(geoms), int(compiler.inertiafromgeom), vec(compiler.inertiagrouprange),
            float(compiler.boundmass), float(compiler.boundinertia), bool(compiler.balanceinertia))


def _freeze_inertia(spec: mujoco.MjSpec, body: mujoco.MjsBody) -> None:
    key = _inertia_key(spec, body)
    cached = _INERTIA_CACHE.get(key)
    if cached is None:
        spec.adopt_inertial(body)
        cached = (float(body.mass), list(body.ipos), list(body.iquat), list(body.inertia), list(body.fullinertia))
        _INERTIA_CACHE[key] = cached
        return
    body.explicitinertial = True
    body.mass, body.ipos, body.iquat, body.inertia, body.fullinertia = cached


def _delete_unused_meshes(spec: mujoco.MjSpec, candidates: set[str]) -> None:
    """Delete the meshes among `candidates` (the replaced visual meshes) that no geom uses any more."""
    used = {g.meshname for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH}
    for name in sorted(candidates - used):
        mesh = spec.mesh(name)
        if mesh is not None:
            spec.delete(mesh)
