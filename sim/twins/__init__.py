"""Sim twins of the hardware: arm (ur_rtde), gripper (Robotiq 2F-85) and cameras (RealSense) on one SimRig."""

from sim.twins.arm import ArmNoiseConfig, SimArm
from sim.twins.camera import CameraNoiseConfig, SimCamera
from sim.twins.gripper import SimGripper
from sim.twins.rig import ProtectiveStopConfig, SimRig

__all__ = ["ArmNoiseConfig", "CameraNoiseConfig", "ProtectiveStopConfig", "SimArm", "SimCamera", "SimGripper", "SimRig"]
