"""Device protocols shared by the real drivers (ur_rtde, Robotiq 2F-85 URCap socket, RealSense) and the sim twins.

Why one module: the runtime talks only to these protocols, and one contract test suite
(`tests/test_device_contract.py`) runs against every implementation, so a policy that works against the twins
meets the same semantics on the real hardware. The semantics follow the real devices:

* Arm: ur_rtde's RTDEControlInterface / RTDEReceiveInterface in snake_case. Commands return False (never
  raise) while the robot is protectively stopped, as ur_rtde does; bad arguments raise ValueError naming the
  argument and its allowed range, before anything reaches the robot. Poses are UR's [x, y, z, rx, ry, rz]
  with a rotation vector, in the controller's base frame. Modes use UR's RTDE integer codes.
* Gripper: normalised Robotiq registers: position 0 = open .. 1 = closed (register 0..255), speed and force
  0..1 of the gripper's range. `object_detected` mirrors gOBJ = 1/2 (fingers stopped on an object).
* Camera: colour uint8 HxWx3 (RGB) and depth uint16 HxW in millimetres aligned to colour (0 = no data), as
  a RealSense with `align_to(color)` delivers; `capture_ns` is the capture time on the host's monotonic clock.

This module must not import mujoco: real drivers import it on machines without the simulator.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from sim.camera_model import Intrinsics

# ur_rtde's accepted ranges for servoJ (the controller rejects values outside them).
SERVO_LOOKAHEAD_RANGE = (0.03, 0.2)  # s
SERVO_GAIN_RANGE = (100.0, 2000.0)  # proportional gain
UNLOCK_DELAY_S = 5.0  # the controller refuses to unlock a protective stop earlier than this


class RobotMode(enum.IntEnum):
    """UR robot modes (RTDE `robot_mode` codes)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(enum.IntEnum):
    """UR safety modes (RTDE `safety_mode` codes)."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9


@dataclass(frozen=True)
class ArmState:
    """One sample of the arm's receive interface (getActualQ, getActualQd, getActualTCPPose, getTargetQ...)."""

    q: np.ndarray  # (6,) rad, actual joint positions
    qd: np.ndarray  # (6,) rad/s, actual joint velocities
    tcp_pose: np.ndarray  # (6,) [x, y, z, rx, ry, rz]: metres and rotation vector, base frame
    target_q: np.ndarray  # (6,) rad, the controller's current joint target (after its interpolation)
    timestamp_ns: int  # host monotonic time of the sample (the twin's rig clock in simulation)
    robot_mode: RobotMode = RobotMode.RUNNING
    safety_mode: SafetyMode = SafetyMode.NORMAL
    speed_scaling: float = 1.0  # the controller's speed slider x safety scaling, 0..1
    # getActualTCPForce: [Fx, Fy, Fz, Tx, Ty, Tz] (N, N m), base frame, the external load on the tool (the
    # payload's own weight compensated); None where the source cannot report it (an old recording)
    tcp_force: np.ndarray | None = None

    @property
    def is_protective_stopped(self) -> bool:
        return self.safety_mode == SafetyMode.PROTECTIVE_STOP

    @property
    def is_emergency_stopped(self) -> bool:
        return self.safety_mode in (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP)


@runtime_checkable
class ArmDriver(Protocol):
    """A UR arm driven over RTDE. Motion commands return True when accepted, False while stopped."""

    @property
    def control_period(self) -> float:
        """Seconds per controller cycle (0.002 on e-Series, 0.008 on CB3)."""

    def servo_j(self, q, velocity: float = 0.5, acceleration: float = 0.5, time: float = 0.002,
                lookahead_time: float = 0.1, gain: float = 300.0) -> bool:
        """Stream one joint target (non-blocking); call once per control period. velocity/acceleration are
        accepted for ur_rtde compatibility and unused, as on the real controller."""

    def speed_j(self, qd, acceleration: float = 0.5, time: float = 0.0) -> bool:
        """Accelerate to joint velocity `qd`; `time` > 0 ends the command after that long (0: until replaced)."""

    def move_j(self, q, speed: float = 1.05, acceleration: float = 1.4) -> bool:
        """Trapezoidal joint move; blocks until the goal is reached. False if stopped on the way."""

    def servo_stop(self, deceleration: float = 10.0) -> None:
        """Leave servo mode, decelerating (rad/s^2)."""

    def speed_stop(self, deceleration: float = 10.0) -> None:
        """Leave speed mode, decelerating (rad/s^2)."""

    def stop(self, deceleration: float = 2.0) -> None:
        """stopJ: decelerate whatever motion is running to rest; blocks until at rest."""

    def init_period(self) -> int:
        """ur_rtde initPeriod: the start time (ns) of a control cycle, for `wait_period`."""

    def wait_period(self, t_start_ns: int) -> None:
        """ur_rtde waitPeriod: sleep until one control period after `t_start_ns` (in lock-step sim: step)."""

    def state(self) -> ArmState: ...

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop; False (and still stopped) within UNLOCK_DELAY_S of the stop."""

    def close(self) -> None:
        """Stop the control script and disconnect."""


@dataclass(frozen=True)
class GripperState:
    position: float  # measured finger closure, 0 open .. 1 closed
    target: float  # last commanded position
    is_moving: bool
    object_detected: bool  # fingers stopped on an object before reaching the target (gOBJ 1 or 2)
    timestamp_ns: int
    is_activated: bool = True


@runtime_checkable
class GripperDriver(Protocol):
    """A Robotiq 2F-85 (normalised registers). Commands before `activate()` are refused (return False)."""

    def activate(self) -> None: ...

    def move(self, position: float, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        """Go to `position` (0 open .. 1 closed) at `speed`, squeezing with `force` (both 0..1). With
        `wait`, block until the fingers stop (at the target or on an object). True if the command was accepted."""

    def open(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool: ...

    def close(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool: ...

    def state(self) -> GripperState: ...

    def disconnect(self) -> None: ...


class StaleFrameError(RuntimeError):
    """The newest frame is older than the caller accepts (camera stalled, dropped or not started)."""


@dataclass(frozen=True)
class Frame:
    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray | None  # (H, W) uint16 millimetres aligned to colour, 0 = no data; None if no depth stream
    intrinsics: Intrinsics  # of the colour stream (and of the aligned depth)
    camera_id: str
    seq: int  # frame number from the device, strictly increasing
    capture_ns: int  # host monotonic time of the exposure

    def age_s(self, now_ns: int) -> float:
        return (now_ns - self.capture_ns) * 1e-9


@runtime_checkable
class CameraDriver(Protocol):
    name: str

    def intrinsics(self, stream: str = "color") -> Intrinsics:
        """`color` or `depth`; depth is aligned to colour, so both are the colour intrinsics."""

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def read(self, timeout_s: float = 1.0) -> Frame:
        """Block for the next frame newer than the last one returned; TimeoutError after `timeout_s`."""

    def read_latest(self, max_age_s: float) -> Frame:
        """The newest frame without waiting; StaleFrameError if none is younger than `max_age_s`."""


# -- argument checks shared by every implementation (same messages on sim and hardware) -------------------
def check_vector(name: str, value, n: int = 6, lo=None, hi=None, unit: str = "") -> np.ndarray:
    """`value` as a finite float (n,) array inside [lo, hi] (scalars or per-element arrays)."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    lo_a = None if lo is None else np.broadcast_to(np.asarray(lo, float), (n,))
    hi_a = None if hi is None else np.broadcast_to(np.asarray(hi, float), (n,))
    if (lo_a is not None and np.any(arr < lo_a)) or (hi_a is not None and np.any(arr > hi_a)):
        rng = f"[{_fmt(lo_a, '-inf')}, {_fmt(hi_a, 'inf')}]" + (f" {unit}" if unit else "")
        raise ValueError(f"{name} = {np.round(arr, 4).tolist()} is out of range; allowed: {rng}")
    return arr


def check_scalar(name: str, value, lo: float | None = None, hi: float | None = None, unit: str = "") -> float:
    """`value` as a finite float inside [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]" + (f" {unit}" if unit else "")
        raise ValueError(f"{name} = {value!r} is out of range; allowed: {rng}")
    return v


def _fmt(a, default: str) -> str:
    if a is None:
        return default
    return str(float(a[0])) if np.all(a == a[0]) else str(np.round(a, 4).tolist())
