"""Robot variants (UR5e, UR5/CB3) and their MuJoCo assembly with the Robotiq 2F-85 at the flange.

Frames: the MuJoCo world frame is the UR controller's base frame (the frame of `getActualTCPPose`), and the
`flange` site is the tool flange of the standard UR DH chain. Link offsets are written from the variant's DH
parameters, so the MuJoCo model and `sim.kinematics` agree by construction (a test checks it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from sim.assets import robotiq_2f85_xml, ur5e_xml

ARM_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
ARM_ACTUATORS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
ARM_BODIES = ("base", "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
GRIPPER_PREFIX = "gripper/"
GRIPPER_ACTUATOR = GRIPPER_PREFIX + "fingers_actuator"
GRIPPER_DRIVER_JOINTS = (GRIPPER_PREFIX + "right_driver_joint", GRIPPER_PREFIX + "left_driver_joint")
GRIPPER_PAD_GEOMS = tuple(GRIPPER_PREFIX + f"{side}_pad{i}" for side in ("left", "right") for i in (1, 2))
FLANGE_SITE = "flange"
TCP_SITE = "tcp"
WRIST_CAMERA = GRIPPER_PREFIX + "wrist_cam"

# Distance from the tool flange to the point between the 2F-85 fingertips, along the flange z axis:
# coupling plate 7 mm + base offset 3.8 mm + Menagerie's pinch point 145 mm.
TCP_OFFSET_Z = 0.007 + 0.0038 + 0.145
GRIPPER_MAX_DRIVER = 0.8  # rad, 2F-85 driver joint travel (fully closed)
GRIPPER_STROKE = 0.085  # m, fully open finger gap

# Joint servo gains (N·m/rad, N·m·s/rad). Menagerie's kv/kp of 0.2 s lags 0.1 rad at 0.5 rad/s; a real UR
# tracks servoJ targets within milliradians, so the servos are stiffer with kv/kp = 0.02 s (still stable at
# the 2 ms step with implicit damping).
SERVO_KP = (20000.0, 20000.0, 20000.0, 2000.0, 2000.0, 2000.0)
SERVO_KV = (400.0, 400.0, 400.0, 40.0, 40.0, 40.0)

# Menagerie's shoulder and elbow lateral offsets; the wrist_2 offset makes up d4 from them.
_SHOULDER_Y = 0.138
_UR5E_D1 = 0.163  # the d1 Menagerie's UR5e meshes and capsules were drawn for
_ELBOW_Y = -0.131


@dataclass(frozen=True)
class RobotVariant:
    """One UR arm model: DH parameters (standard convention, metres), limits and controller rate."""

    name: str
    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float
    control_hz: int
    joint_lower: tuple[float, ...]
    joint_upper: tuple[float, ...]
    max_joint_velocity: tuple[float, ...]
    max_joint_torque: tuple[float, ...]
    home: tuple[float, ...] = (-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    description: str = field(default="", compare=False)

    @property
    def dh_d(self) -> np.ndarray:
        return np.array([self.d1, 0.0, 0.0, self.d4, self.d5, self.d6])

    @property
    def dh_a(self) -> np.ndarray:
        return np.array([0.0, self.a2, self.a3, 0.0, 0.0, 0.0])

    @property
    def dh_alpha(self) -> np.ndarray:
        return np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

    @property
    def control_period(self) -> float:
        return 1.0 / self.control_hz


_TWO_PI = 2 * np.pi
_LIMITS = dict(
    joint_lower=(-_TWO_PI, -_TWO_PI, -np.pi, -_TWO_PI, -_TWO_PI, -_TWO_PI),
    joint_upper=(_TWO_PI, _TWO_PI, np.pi, _TWO_PI, _TWO_PI, _TWO_PI),
    max_joint_velocity=(np.pi,) * 6,
)

VARIANTS: dict[str, RobotVariant] = {
    "ur5e": RobotVariant(
        name="ur5e",
        d1=0.1625, a2=-0.425, a3=-0.3922, d4=0.1333, d5=0.0997, d6=0.0996,
        control_hz=500,
        max_joint_torque=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
        description="UR5e (e-Series), nominal DH from Universal Robots, 500 Hz RTDE",
        **_LIMITS,
    ),
    "ur5": RobotVariant(
        name="ur5",
        d1=0.089159, a2=-0.425, a3=-0.39225, d4=0.10915, d5=0.09465, d6=0.0823,
        control_hz=125,
        max_joint_torque=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
        description="UR5 (CB3), nominal DH from Universal Robots, 125 Hz RTDE; drawn with the UR5e meshes",
        **_LIMITS,
    ),
}


def get_variant(name: str) -> RobotVariant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"unknown robot variant {name!r}; expected one of {sorted(VARIANTS)}") from None


def robot_spec(variant: RobotVariant | str = "ur5e") -> mujoco.MjSpec:
    """The arm with the 2F-85 attached at the flange, as an MjSpec ready to attach into a scene.

    The arm and gripper bodies carry gravity compensation, as the real controller compensates gravity and
    the payload; this keeps joint tracking close to a real UR's without absurd gains.
    """
    if isinstance(variant, str):
        variant = get_variant(variant)
    spec = mujoco.MjSpec.from_file(str(ur5e_xml()))
    for light in list(spec.lights):
        spec.delete(light)  # the scene owns the lights (and randomizes them)

    spec.body("shoulder_link").pos = [0.0, 0.0, variant.d1]
    # Menagerie's shoulder capsule hangs 4 cm below the shoulder joint of a UR5e; keep its bottom on the
    # base for arms with another d1 (the CB3 UR5's shoulder sits 7 cm lower).
    for geom in spec.body("shoulder_link").geoms:
        if geom.classname.name == "collision":
            geom.pos = [0.0, 0.0, -0.04 + (_UR5E_D1 - variant.d1)]
    spec.body("upper_arm_link").pos = [0.0, _SHOULDER_Y, 0.0]
    spec.body("forearm_link").pos = [0.0, _ELBOW_Y, -variant.a2]
    spec.body("wrist_1_link").pos = [0.0, 0.0, -variant.a3]
    spec.body("wrist_2_link").pos = [0.0, variant.d4 - (_SHOULDER_Y + _ELBOW_Y), 0.0]
    spec.body("wrist_3_link").pos = [0.0, 0.0, variant.d5]
    attachment = spec.site("attachment_site")
    attachment.pos = [0.0, variant.d6, 0.0]
    attachment.name = FLANGE_SITE

    for name, kp, kv in zip(ARM_ACTUATORS, SERVO_KP, SERVO_KV):
        act = spec.actuator(name)
        act.gainprm[0] = kp
        act.biasprm[:3] = [0.0, -kp, -kv]

    wrist3 = spec.body("wrist_3_link")
    # The TCP: flange frame shifted along its z axis, which in wrist_3 coordinates is +y.
    wrist3.add_site(name=TCP_SITE, pos=[0.0, variant.d6 + TCP_OFFSET_Z, 0.0], quat=list(attachment.quat),
                    size=[0.004, 0, 0], group=4, rgba=[1, 0, 0, 0.5])

    set_contact_options(spec)
    gripper = mujoco.MjSpec.from_file(str(robotiq_2f85_xml()))
    for geom in gripper.geoms:
        if "_pad" in geom.name:
            # Silicone pads on a hard object: friction ~1 with torsional friction (condim 4) keeps a grasp
            # through the arm's accelerations. (Set on the geoms: changing the default class after the file
            # is parsed would not reach them.)
            geom.friction = [1.2, 0.01, 0.001]
            geom.condim = 4
    actuator = gripper.actuator("fingers_actuator")
    actuator.forcerange = [-20.0, 20.0]  # a firmer squeeze than Menagerie's 5 N default, as the real 2F-85
    base = gripper.body("base")
    # A wrist camera on the gripper housing, looking along the approach direction (D405-style mount).
    base.add_camera(name=WRIST_CAMERA.removeprefix(GRIPPER_PREFIX), pos=[0.085, 0.0, 0.02], quat=_wrist_camera_quat(), fovy=75.0)
    attachment.attach_body(gripper.body("base_mount"), GRIPPER_PREFIX, "")

    for body in spec.bodies:
        if body.name == "world":
            continue
        body.gravcomp = 1.0
    for key in list(spec.keys):
        spec.delete(key)  # its qpos would not fit the scene; scenes set the home pose themselves
    return spec


def set_contact_options(spec: mujoco.MjSpec) -> None:
    """Solver options that let the 2F-85 hold objects without slip (the gripper model's own choice)."""
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.timestep = 0.002  # 500 Hz: one physics step per e-Series control cycle


def _wrist_camera_quat() -> list[float]:
    # Mounted beside the housing, off the finger plane, looking along the approach axis and tilted
    # towards it so the fingertips sit in the lower part of the image; image up points away from the axis.
    tilt = np.deg2rad(28.0)
    z_cam = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])  # MuJoCo cameras look along their -z
    y_cam = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    x_cam = np.cross(y_cam, z_cam)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([x_cam, y_cam, z_cam]).flatten())
    return quat.tolist()
