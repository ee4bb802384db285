"""A compiled scene: MuJoCo model and data plus the robot's named handles (joints, actuators, sites)."""

from __future__ import annotations

import mujoco
import numpy as np

from sim.finger_drive import FingerDrive, force_register, speed_register
from sim.robot import (
    ARM_ACTUATORS,
    ARM_JOINTS,
    FLANGE_SITE,
    GRIPPER_ACTUATOR,
    GRIPPER_DRIVER_JOINTS,
    GRIPPER_MAX_DRIVER,
    TCP_SITE,
    RobotVariant,
    get_variant,
)

GRIPPER_CTRL_MAX = 255.0  # the 2F-85 actuator takes the Robotiq register scale 0 (open) .. 255 (closed)


class World:
    """One simulated scene. Physics steps at the model's timestep (2 ms: one e-Series control cycle)."""

    def __init__(self, model: mujoco.MjModel, variant: RobotVariant | str = "ur5e", info: dict | None = None):
        self.model = model
        self.data = mujoco.MjData(model)
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        self.info = dict(info or {})  # what built this world: task, seed, DR parameters
        jid = [model.joint(n).id for n in ARM_JOINTS]
        self.arm_qpos_adr = np.array([model.jnt_qposadr[j] for j in jid])
        self.arm_dof_adr = np.array([model.jnt_dofadr[j] for j in jid])
        self.arm_actuators = np.array([model.actuator(n).id for n in ARM_ACTUATORS])
        self.gripper_actuator = model.actuator(GRIPPER_ACTUATOR).id
        self.gripper_qpos_adr = np.array([model.jnt_qposadr[model.joint(n).id] for n in GRIPPER_DRIVER_JOINTS])
        self.tcp_site = model.site(TCP_SITE).id
        self.flange_site = model.site(FLANGE_SITE).id
        self.fingers: FingerDrive | None = None  # set by drive_fingers(): the fingers move as the driver moves them
        self.reset()

    # -- state -----------------------------------------------------------------------------------
    def reset(self, arm_q=None) -> None:
        """Back to the model's initial state with the arm at `arm_q` (default: the variant's home)."""
        mujoco.mj_resetData(self.model, self.data)
        q = np.asarray(self.variant.home if arm_q is None else arm_q, dtype=float)
        self.data.qpos[self.arm_qpos_adr] = q
        self.data.ctrl[self.arm_actuators] = q
        mujoco.mj_forward(self.model, self.data)

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    def arm_q(self) -> np.ndarray:
        return self.data.qpos[self.arm_qpos_adr].copy()

    def arm_qd(self) -> np.ndarray:
        return self.data.qvel[self.arm_dof_adr].copy()

    def arm_torque(self) -> np.ndarray:
        return self.data.actuator_force[self.arm_actuators].copy()

    def set_arm_target(self, q) -> None:
        """Joint position targets for the arm's servo actuators (clipped to their control range)."""
        lo = self.model.actuator_ctrlrange[self.arm_actuators, 0]
        hi = self.model.actuator_ctrlrange[self.arm_actuators, 1]
        self.data.ctrl[self.arm_actuators] = np.clip(q, lo, hi)

    def arm_target(self) -> np.ndarray:
        return self.data.ctrl[self.arm_actuators].copy()

    def set_gripper(self, closing: float) -> None:
        """Gripper command in [0, 1]: 0 fully open, 1 fully closed (it stops on an object)."""
        self.data.ctrl[self.gripper_actuator] = float(np.clip(closing, 0.0, 1.0)) * GRIPPER_CTRL_MAX

    def gripper_command(self) -> float:
        """The actuator's command in [0, 1] (with a finger drive: the point its ramp has reached)."""
        return float(self.data.ctrl[self.gripper_actuator] / GRIPPER_CTRL_MAX)

    def drive_fingers(self, speed_m_s: float, force_n: float) -> FingerDrive:
        """From now on the fingers move as the 2F-85's driver moves them, at this speed and force
        (sim/finger_drive.py); whoever steps the world calls `fingers.command` and `fingers.update`."""
        self.fingers = FingerDrive(self)
        self.fingers.set(speed_register(speed_m_s), force_register(force_n))
        return self.fingers

    def gripper_goal(self) -> float:
        """The closure asked for in [0, 1]: the finger drive's target, or the actuator's command without one."""
        return self.fingers.target if self.fingers is not None else self.gripper_command()

    def gripper_position(self) -> float:
        """Measured finger closure in [0, 1] from the driver joints (0 open, 1 closed)."""
        return float(np.clip(self.data.qpos[self.gripper_qpos_adr].mean() / GRIPPER_MAX_DRIVER, 0.0, 1.0))

    def site_pose(self, site_id: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[site_id].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[site_id]
        return T

    def tcp_pose(self) -> np.ndarray:
        """Base-frame 4x4 pose of the TCP (between the fingertips)."""
        return self.site_pose(self.tcp_site)

    # -- time --------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        mujoco.mj_step(self.model, self.data, nstep=n)

    def forward(self) -> None:
        mujoco.mj_forward(self.model, self.data)
