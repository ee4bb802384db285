"""safety: the layer every arm command passes through — limits, per-cycle filter, collision guard, stops.

    from safety import SafetyFilter, default_limits
    f = SafetyFilter(default_limits("ur5e"))
    r = f.step(desired_q, measured_q, measured_qd, now, command_time)   # r.q is safe to send

Imports are lazy: `import safety` loads nothing heavy (no MuJoCo); each name loads its module on first use.
`safety/` imports only numpy, mujoco (collision guard) and sim.robot / sim.rotations / sim.config / sim.scene.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "SafetyLimits": "safety.limits", "JointLimits": "safety.limits", "WorkspaceLimits": "safety.limits",
    "TcpLimits": "safety.limits", "CommandLimits": "safety.limits", "CollisionLimits": "safety.limits",
    "GripperLimits": "safety.limits", "RecoveryLimits": "safety.limits", "default_limits": "safety.limits",
    "load_limits": "safety.limits",
    "SafetyEvent": "safety.events", "EventCoalescer": "safety.events",
    "SafetyFilter": "safety.filter", "FilterResult": "safety.filter",
    "JointLimiter": "safety.joint_limits",
    "Workspace": "safety.workspace",
    "FastKinematics": "safety.fastfk",
    "CollisionGuard": "safety.collision", "CollisionCheck": "safety.collision",
    "CommandWatchdog": "safety.watchdog",
    "vec6": "safety.inputs", "parse_pose": "safety.inputs",
    "StopStateMachine": "safety.stop_states",
    "GripperCommand": "safety.gripper", "limit_gripper": "safety.gripper",
    "run_safety_bench": "safety.bench",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'safety' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(list(globals()) + __all__)
