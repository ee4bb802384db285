"""The static world around the robot: floor, table, walls, lights and the fixed scene camera.

Layout (metres, world = robot base frame): the robot stands on the table top (z = 0) at the origin and faces
+y; the task area is x in [-0.35, 0.35], y in [0.3, 0.75]; the scene camera stands across the table and looks
back at the robot, as a RealSense on a tripod would.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sim.camera_model import D435_COLOR
from sim.robot import RobotVariant, get_variant, robot_spec

SCENE_CAMERA = "scene_cam"
TABLE_TOP_Z = 0.0
TABLE_HALF = (0.75, 0.65, 0.02)
TABLE_CENTRE = (0.0, 0.35)
FLOOR_Z = -0.74
TASK_AREA = ((-0.35, 0.35), (0.30, 0.75))  # (x range, y range) where task objects are placed
SURFACES = ("table", "floor", "wall")  # materials that domain randomization retextures


@dataclass(frozen=True)
class CameraPose:
    """A camera placed by its position and the point it looks at, with image-up roughly +z."""

    pos: tuple[float, float, float]
    target: tuple[float, float, float]
    fovy_deg: float

    def quat(self) -> list[float]:
        forward = np.asarray(self.target, float) - np.asarray(self.pos, float)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        # MuJoCo cameras look along -z with +y up in the image.
        mat = np.column_stack([right, up, -forward])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, mat.flatten())
        return quat.tolist()


DEFAULT_SCENE_CAMERA = CameraPose(pos=(0.0, 1.55, 1.00), target=(0.0, 0.25, 0.15), fovy_deg=D435_COLOR.fovy_deg)
DEFAULT_LIGHTS = (((0.6, 0.9, 1.6), 0.55), ((-0.8, -0.2, 1.8), 0.35))


def base_scene(variant: RobotVariant | str = "ur5e") -> mujoco.MjSpec:
    """Table, floor, walls, two lights, the scene camera and the robot with its gripper."""
    if isinstance(variant, str):
        variant = get_variant(variant)
    spec = robot_spec(variant)  # the robot base is the world origin, standing on the table top
    spec.modelname = f"sudd_{variant.name}"
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    spec.stat.center = [0.0, 0.4, 0.1]
    spec.stat.extent = 1.2

    for surface, rgb1, rgb2 in (("table", (0.55, 0.42, 0.3), (0.5, 0.38, 0.27)),
                                ("floor", (0.3, 0.3, 0.32), (0.25, 0.25, 0.27)),
                                ("wall", (0.75, 0.75, 0.72), (0.7, 0.7, 0.68))):
        spec.add_texture(name=f"{surface}_tex", type=mujoco.mjtTexture.mjTEXTURE_2D,
                         builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=list(rgb1), rgb2=list(rgb2),
                         width=64, height=64)
        mat = spec.add_material(name=f"{surface}_mat", texrepeat=[4, 4], reflectance=0.0)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{surface}_tex"

    world = spec.worldbody
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.5], pos=[0, 0, FLOOR_Z],
                   material="floor_mat")
    tx, ty = TABLE_CENTRE
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(TABLE_HALF),
                   pos=[tx, ty, TABLE_TOP_Z - TABLE_HALF[2]], material="table_mat", friction=[0.8, 0.005, 0.0001])
    for name, pos, size in (("wall_back", [0, -1.4, 0.5], [2.5, 0.02, 1.3]),
                            ("wall_left", [-1.8, 0.3, 0.5], [0.02, 2.5, 1.3]),
                            ("wall_right", [1.8, 0.3, 0.5], [0.02, 2.5, 1.3])):
        world.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, size=size, material="wall_mat",
                       contype=0, conaffinity=0)
    for i, (pos, intensity) in enumerate(DEFAULT_LIGHTS):
        add_light(spec, i, pos, intensity)
    add_scene_camera(spec, DEFAULT_SCENE_CAMERA)
    return spec


def add_light(spec: mujoco.MjSpec, index: int, pos, intensity: float, castshadow: bool = True) -> mujoco.MjsLight:
    target = np.array([0.0, 0.45, 0.0]) - np.asarray(pos)
    return spec.worldbody.add_light(name=f"light{index}", pos=list(pos), dir=(target / np.linalg.norm(target)).tolist(),
                                    diffuse=[intensity] * 3, specular=[0.1, 0.1, 0.1], castshadow=castshadow,
                                    cutoff=60.0, exponent=1.0)


def add_scene_camera(spec: mujoco.MjSpec, pose: CameraPose) -> mujoco.MjsCamera:
    return spec.worldbody.add_camera(name=SCENE_CAMERA, pos=list(pose.pos), quat=pose.quat(), fovy=pose.fovy_deg)
