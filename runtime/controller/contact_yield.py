"""ContactYield: the commanded pose gives way along the tool force the arm measures, before it becomes a stop.

Why: the UR is a stiff position-controlled arm. A policy whose chunk is a centimetre off where the world is
stiff (a cabinet front, the table) turns that centimetre into hundreds of newtons, and the robot's own force
limit (150 N by default) ends the task in a protective stop: the cause of 23 of 27 failed drawer episodes
(policy/EXPERIMENTS.md, "The wider denoiser on this CPU"). A person's hand gives way instead and lets the
next look correct the error. This is that hand, as an admittance on the streamed targets:

* above `contact_yield_n` of measured tool force (getActualTCPForce, the flange sensor with the payload
  compensated), the planned motion into the contact is cancelled and the target retreats along the force at
  `contact_yield_gain` per newton of excess (at most `contact_yield_speed`): the press settles at about
  `contact_yield_n`;
* below half of it the offset returns to the plan at `contact_return_speed`, so a plan that still presses
  comes back to a gentle press rather than springing into the contact;
* the offset is capped at `contact_max_offset`: past that the plan is really wrong, and the robot's own
  force limit is the right answer.

What it cannot do: an impact. A finger that meets a stiff front at the policy's approach speed builds its
force within a physics step, before any measured force can act; that is what still stops the drawer
episodes, so it is off by default (ControllerConfig.contact_yield_n; set e.g. 40 N in `--controller FILE`).

Only the position gives way (orientation follows the plan); the offset is mapped to joints through the
damped Jacobian pseudo-inverse at the planned joints, and the result still goes through the safety filter
like every other target. Why not UR's force mode: force control running in the UR controller bypasses the
streamed, filtered targets that this runtime's safety layer is built on, and it has no sim twin here.
"""

from __future__ import annotations

import math

import numpy as np

_DAMPING = 1e-3  # m: keeps the pseudo-inverse bounded near a singularity


class ContactYield:
    def __init__(self, cfg, kin, period: float):
        self.cfg, self.kin, self.dt = cfg, kin, float(period)
        self.offset = np.zeros(3)
        self.yielding = False
        self._prev_p: np.ndarray | None = None

    @property
    def enabled(self) -> bool:
        return self.cfg.contact_yield_n > 0.0

    def reset(self) -> None:
        """Forget the offset (a stop dropped the plan the offset was relative to)."""
        self.offset[:] = 0.0
        self._prev_p, self.yielding = None, False

    def apply(self, desired_q: np.ndarray, tcp_force) -> tuple[np.ndarray, str | None]:
        """The joint target with the offset applied, and "start" / "end" when yielding starts or ends."""
        if not self.enabled or tcp_force is None:
            return desired_q, None
        f = np.asarray(tcp_force, dtype=float)[:3]
        if self.cfg.contact_yield_axes == "up":
            f = np.array([0.0, 0.0, max(float(f[2]), 0.0)])
        mag = float(math.sqrt(f @ f)) if np.all(np.isfinite(f)) else 0.0
        cfg = self.cfg
        if mag <= 0.5 * cfg.contact_yield_n and not self.offset.any():
            self._prev_p = None
            return self._transition(False, desired_q)
        p = self.kin.fk(desired_q)[:3, 3]
        dp = np.zeros(3) if self._prev_p is None else p - self._prev_p
        self._prev_p = p
        if mag > cfg.contact_yield_n:
            n = f / mag
            into = -float(dp @ n)  # the plan's step into the contact this cycle: not taken
            retreat = min(cfg.contact_yield_gain * (mag - cfg.contact_yield_n), cfg.contact_yield_speed) * self.dt
            self.offset += n * (max(into, 0.0) + retreat)
        elif mag < 0.5 * cfg.contact_yield_n:
            size = float(np.linalg.norm(self.offset))
            back = cfg.contact_return_speed * self.dt
            self.offset = np.zeros(3) if size <= back else self.offset * (1.0 - back / size)
        size = float(np.linalg.norm(self.offset))
        if size > cfg.contact_max_offset:
            self.offset *= cfg.contact_max_offset / size
        if not self.offset.any():
            return self._transition(False, desired_q)
        J = self.kin.jacobian(desired_q)
        v = np.concatenate([self.offset, np.zeros(3)])
        dq = J.T @ np.linalg.solve(J @ J.T + _DAMPING ** 2 * np.eye(6), v)
        return self._transition(True, desired_q + dq)

    def _transition(self, yielding: bool, q: np.ndarray) -> tuple[np.ndarray, str | None]:
        change = None if yielding == self.yielding else ("start" if yielding else "end")
        self.yielding = yielding
        return q, change


__all__ = ["ContactYield"]
