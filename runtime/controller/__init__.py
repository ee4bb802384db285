"""runtime.controller: action chunks -> smooth joint targets at the servo rate, through the safety filter.

    from runtime.controller import ControllerLoop, ControllerConfig
    loop = ControllerLoop(arm, gripper, SafetyFilter(default_limits("ur5e")), ControllerConfig())

Modules, one job each: `config` (knobs), `ik_follow` (chunk -> joint knots on the current IK branch),
`interpolate` (C2 splines, blends, stop curves), `schedule` (the timeline of targets and chunk takeover),
`gripper` (channel -> open/close with hysteresis), `recovery` (protective-stop sequence), `latency`
(cross-correlation estimate), `telemetry` (per-cycle ring buffer), `loop` (the control cycle), `runner`
(pacing at the control rate, the background thread and the controlled stop).
No torch here: the runtime side never imports the policy's framework.
"""

from runtime.controller.config import ControllerConfig, load_controller, with_bundle_levels
from runtime.controller.ik_follow import ChunkRejected, JointChunk
from runtime.controller.loop import ControllerLoop, CycleResult
from runtime.controller.recovery import RecoveryHooks

__all__ = ["ControllerLoop", "ControllerConfig", "load_controller", "with_bundle_levels", "CycleResult",
           "RecoveryHooks", "ChunkRejected", "JointChunk"]
