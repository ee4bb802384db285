"""SimGripper: the Robotiq 2F-85 twin (GripperDriver) on the MuJoCo 2F-85 model.

Why a ramp: the real 2F-85 moves its fingers at the commanded speed (20-150 mm/s over the 85 mm stroke),
not at whatever a position servo would do, so the twin ramps the actuator command at that rate and the
MuJoCo servo follows it. Force scales the actuator's force limit (the real gripper's 20-235 N maps to
10-100 % of the model's limit). Like gOBJ, `object_detected` is set when the fingers have stopped short of
their target (closing or opening) with a finger pad touching something that is not the robot.
"""

from __future__ import annotations

import numpy as np

from sim.devices import GripperState, check_scalar
from sim.robot import GRIPPER_STROKE

SPEED_RANGE_M_S = (0.020, 0.150)  # finger speed at speed = 0 and 1
FORCE_MIN_FRACTION = 0.1  # force = 0 gives this fraction of the model's force limit
_AT_TARGET_TOL = 0.03  # measured position within this of the target counts as "at the target"
_STILL_SPEED = 0.05  # rad/s of the driver joints: below this the fingers count as stopped
_STILL_CYCLES = 10  # ...for this many consecutive cycles
_WAIT_TIMEOUT_S = 5.0


class SimGripper:
    """GripperDriver twin; create it through `SimRig`."""

    def __init__(self, rig):
        self._rig, self._world = rig, rig.world
        m = self._world.model
        self._dof = np.array([m.jnt_dofadr[m.jnt_qposadr.tolist().index(a)] for a in self._world.gripper_qpos_adr])
        self._act = self._world.gripper_actuator
        self._force_limit = m.actuator_forcerange[self._act].copy()
        self._activated = False
        self._target = self._cmd = self._world.gripper_command()
        self._rate = 0.0
        self._moving = False
        self._still = 0
        self._object = False

    def activate(self) -> None:
        with self._rig.lock:
            self._activated = True

    def move(self, position: float, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        position = check_scalar("position", position, 0.0, 1.0)
        speed = check_scalar("speed", speed, 0.0, 1.0)
        force = check_scalar("force", force, 0.0, 1.0)
        with self._rig.lock:
            if not self._activated:
                return False
            lo, hi = SPEED_RANGE_M_S
            self._rate = (lo + speed * (hi - lo)) / GRIPPER_STROKE  # stroke fraction per second
            scale = FORCE_MIN_FRACTION + (1.0 - FORCE_MIN_FRACTION) * force
            self._world.model.actuator_forcerange[self._act] = self._force_limit * scale
            self._target = position
            self._cmd = self._world.gripper_position()  # the ramp starts where the fingers are
            self._moving, self._still, self._object = True, 0, False
        if wait:
            self._rig.wait_until(lambda: not self._moving, _WAIT_TIMEOUT_S)
        return True

    def open(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        return self.move(0.0, speed, force, wait)

    def close(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        return self.move(1.0, speed, force, wait)

    def state(self) -> GripperState:
        with self._rig.lock:
            return GripperState(position=self._world.gripper_position(), target=self._target, is_moving=self._moving,
                                object_detected=self._object, timestamp_ns=self._rig.sample_ns,
                                is_activated=self._activated)

    def disconnect(self) -> None:
        pass

    # -- called by the rig each control cycle (lock held) ---------------------------------------------------
    def _update(self, dt: float) -> None:
        step = self._rate * dt
        self._cmd += float(np.clip(self._target - self._cmd, -step, step))
        self._world.set_gripper(self._cmd)
        if not (self._moving or self._object):
            return
        if np.max(np.abs(self._world.data.qvel[self._dof])) >= _STILL_SPEED:
            self._still, self._moving, self._object = 0, True, False
            return
        self._still += 1
        if self._still < _STILL_CYCLES:
            return
        touching = abs(self._world.gripper_position() - self._target) > _AT_TARGET_TOL and self._pads_touch_object()
        if touching or abs(self._cmd - self._target) < 1e-9:  # stopped on an object, or the ramp is done
            self._moving, self._object = False, touching

    def _pads_touch_object(self) -> bool:
        d, rig = self._world.data, self._rig
        n = d.ncon
        if n == 0:
            return False
        g = d.contact.geom[:n]
        g1, g2 = g[:, 0], g[:, 1]
        hit = (rig.geom_pad[g1] & ~rig.geom_robot[g2]) | (rig.geom_pad[g2] & ~rig.geom_robot[g1])
        return bool(np.any(hit))
