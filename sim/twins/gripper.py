"""SimGripper: the Robotiq 2F-85 twin (GripperDriver) on the MuJoCo 2F-85 model.

The fingers move as the real driver moves them, at the commanded speed and squeezing with the commanded force
(sim/finger_drive.py, the model the data collector shares). Like gOBJ, `object_detected` is set when the fingers
have stopped short of their target (closing or opening) with a finger pad touching something that is not the
robot.
"""

from __future__ import annotations

import numpy as np

from sim.devices import GripperState, check_scalar
from sim.finger_drive import STILL_SPEED, FingerDrive

_AT_TARGET_TOL = 0.03  # measured position within this of the target counts as "at the target"
_STILL_CYCLES = 10  # the fingers count as stopped after this many cycles under STILL_SPEED
_WAIT_TIMEOUT_S = 5.0


class SimGripper:
    """GripperDriver twin; create it through `SimRig`."""

    def __init__(self, rig):
        self._rig, self._world = rig, rig.world
        self._drive = FingerDrive(self._world)
        self._activated = False
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
            self._drive.set(speed, force)
            self._drive.command(position)
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
            return GripperState(position=self._world.gripper_position(), target=self._drive.target,
                                is_moving=self._moving, object_detected=self._object, timestamp_ns=self._rig.sample_ns,
                                is_activated=self._activated)

    def disconnect(self) -> None:
        pass

    # -- called by the rig each control cycle (lock held) ---------------------------------------------------
    def _update(self, dt: float) -> None:
        self._drive.update(dt)
        if not (self._moving or self._object):
            return
        if self._drive.moving(STILL_SPEED):
            self._still, self._moving, self._object = 0, True, False
            return
        self._still += 1
        if self._still < _STILL_CYCLES:
            return
        short = abs(self._world.gripper_position() - self._drive.target) > _AT_TARGET_TOL
        touching = short and self._pads_touch_object()
        if touching or not self._drive.ramping:  # stopped on an object, or the ramp is done
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
