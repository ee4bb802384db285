"""The tool wrench a UR e-Series reports (getActualTCPForce), from the simulated contacts on the gripper.

Why from contacts: the real arm measures the wrench with the flange's force/torque sensor and subtracts the
configured payload (tool and gripper weight and inertia), so what it reports is the external load on the
tool. In simulation that external load is exactly the sum of the contact forces on the gripper's geoms from
everything that is not the robot: the table, a cabinet, a drawer handle, an object in the fingers (whose
squeeze cancels between the two fingers and leaves its weight). Contacts on the arm's links are not seen,
as the flange sensor does not see them. Torques are about the TCP, like the force, in the base frame.
"""

from __future__ import annotations

import mujoco
import numpy as np


def tool_wrench(model, data, on_tool: np.ndarray, robot: np.ndarray, tcp: np.ndarray) -> np.ndarray:
    """[Fx, Fy, Fz, Tx, Ty, Tz] (N, N m) exerted on the tool's geoms (`on_tool`, a geom mask) by every geom
    outside `robot` (a geom mask), base frame, torque about the point `tcp` (3,)."""
    out = np.zeros(6)
    n = data.ncon
    if n == 0:
        return out
    g = data.contact.geom[:n]
    g1, g2 = g[:, 0], g[:, 1]
    tool_first = on_tool[g1] & ~robot[g2]
    tool_second = on_tool[g2] & ~robot[g1]
    f6 = np.zeros(6)
    for i in np.flatnonzero(tool_first | tool_second):
        c = data.contact[i]
        mujoco.mj_contactForce(model, data, i, f6)
        f = c.frame.reshape(3, 3).T @ f6[:3]  # the force on geom2, in the world (= base) frame
        if tool_first[i]:
            f = -f
        out[:3] += f
        out[3:] += np.cross(c.pos - tcp, f)
    return out


__all__ = ["tool_wrench"]
