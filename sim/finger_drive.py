"""The 2F-85's fingers as its driver moves them: a ramp at the commanded speed, a squeeze at the commanded force.

Why a ramp: the real 2F-85 moves its fingers at the commanded speed (20-150 mm/s over the 85 mm stroke), not
at whatever a position servo would do, so the drive ramps the actuator command at that rate and the MuJoCo
servo follows it. Force scales the actuator's force limit (the real gripper's 20-235 N maps to 10-100 % of
the model's limit). One model for both users: the SimGripper twin (sim/twins/gripper.py), which the runtime
drives, and the data collector (datagen/trajectory.py), so that demonstrations close and squeeze as the
gripper the policy will run on does (an instant full-force servo shut in 0.1 s where the twin takes 0.65 s,
and held a block with 358 N where the twin's 40 N setting gives 69 N: policy/EXPERIMENTS.md, "The arm waits
for the fingers").
"""

from __future__ import annotations

import numpy as np

from sim.robot import GRIPPER_STROKE

SPEED_RANGE_M_S = (0.020, 0.150)  # finger speed at the driver's speed register 0 and 1
FORCE_RANGE_N = (20.0, 235.0)  # grip force at the driver's force register 0 and 1
FORCE_MIN_FRACTION = 0.1  # force register 0 gives this fraction of the model's force limit
STILL_SPEED = 0.05  # rad/s of the driver joints: below this the fingers count as stopped


def speed_register(speed_m_s: float) -> float:
    """Finger speed in m/s -> the driver's normalised speed (0..1), clipped to the 2F-85's range."""
    lo, hi = SPEED_RANGE_M_S
    return min(1.0, max(0.0, (speed_m_s - lo) / (hi - lo)))


def force_register(force_n: float) -> float:
    """Grip force in N -> the driver's normalised force (0..1), clipped to the 2F-85's range."""
    lo, hi = FORCE_RANGE_N
    return min(1.0, max(0.0, (force_n - lo) / (hi - lo)))


class FingerDrive:
    """Ramps a world's gripper actuator toward a target closure (0 open .. 1 closed).

    `set(speed, force)` takes the driver's normalised registers; `command(target)` starts a move from where
    the fingers are; `update(dt)` advances the ramp one control period. `target` is the closure asked for,
    what a recorder logs as the gripper command (the actuator's own command is the ramp's point)."""

    def __init__(self, world):
        self.world = world
        m = world.model
        self.dof = np.array([m.jnt_dofadr[m.jnt_qposadr.tolist().index(a)] for a in world.gripper_qpos_adr])
        self._act = world.gripper_actuator
        self._force_limit = m.actuator_forcerange[self._act].copy()
        self.target = self._cmd = world.gripper_command()
        self.rate = 0.0  # stroke fraction per second

    def set(self, speed: float, force: float) -> None:
        lo, hi = SPEED_RANGE_M_S
        self.rate = (lo + speed * (hi - lo)) / GRIPPER_STROKE
        scale = FORCE_MIN_FRACTION + (1.0 - FORCE_MIN_FRACTION) * force
        self.world.model.actuator_forcerange[self._act] = self._force_limit * scale

    def command(self, target: float) -> None:
        self.target = float(target)
        self._cmd = self.world.gripper_position()  # the ramp starts where the fingers are

    def update(self, dt: float) -> None:
        step = self.rate * dt
        self._cmd += float(np.clip(self.target - self._cmd, -step, step))
        self.world.set_gripper(self._cmd)

    def moving(self, still_speed: float = STILL_SPEED) -> bool:
        """A driver joint moves at `still_speed` (rad/s) or faster."""
        return bool(np.max(np.abs(self.world.data.qvel[self.dof])) >= still_speed)

    @property
    def ramping(self) -> bool:
        """The ramp has not reached its target yet."""
        return abs(self._cmd - self.target) >= 1e-9
