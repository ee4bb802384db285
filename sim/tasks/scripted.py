"""Scripted motion for the task oracles: top-down grasps, straight descents and min-jerk joint moves.

The oracles drive the World directly (joint targets every 2 ms physics step) with privileged object poses.
They exist to prove each task is solvable in this physics and to exercise the success predicates; data
generation uses datagen's sampling-based primitives instead.
"""

from __future__ import annotations

import numpy as np

from sim.kinematics import Kinematics
from sim.robot import TCP_OFFSET_Z

TOP_DOWN = np.diag([1.0, -1.0, -1.0])  # TCP z pointing down, tool x along world x


def top_down(pos, yaw: float) -> np.ndarray:
    """TCP pose above/at `pos`, approach straight down, fingers closing along the rotated tool x axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ TOP_DOWN
    T[:3, 3] = pos
    return T


def min_jerk(s: np.ndarray) -> np.ndarray:
    return 10 * s**3 - 15 * s**4 + 6 * s**5


class Scripted:
    """Moves a World's arm and gripper in lockstep with physics; every call returns when the motion ends."""

    def __init__(self, world, speed: float = 0.25, joint_speed: float = 1.2, observer=None):
        self.world = world
        self.observer = observer  # called with the world after every physics step (videos, checks)
        self.kin = Kinematics.with_tcp_z(world.variant, TCP_OFFSET_Z)
        self.speed = speed  # m/s for Cartesian moves (the collaborative reduced speed)
        self.joint_speed = joint_speed  # rad/s for joint moves
        self.dt = world.timestep
        self.q_cmd = world.arm_q()

    def _run(self, q_targets: np.ndarray) -> None:
        for q in q_targets:
            self.world.set_arm_target(q)
            self.world.step()
            if self.observer is not None:
                self.observer(self.world)
        self.q_cmd = q_targets[-1].copy()

    def best_yaw(self, yaw: float) -> float:
        """The 2F-85 is symmetric: of yaw and yaw + pi, take the one nearest the current wrist angle."""
        current = np.arctan2(self.kin.fk(self.q_cmd)[1, 0], self.kin.fk(self.q_cmd)[0, 0])
        options = [yaw + k * np.pi for k in (-2, -1, 0, 1, 2)]
        return float(min(options, key=lambda a: abs(np.angle(np.exp(1j * (a - current))))))

    def move_joints(self, q_goal, min_time: float = 0.3) -> None:
        q0 = self.q_cmd.copy()
        q_goal = np.asarray(q_goal, dtype=float)
        span = float(np.max(np.abs(q_goal - q0)))
        duration = max(min_time, 1.875 * span / self.joint_speed)  # min-jerk peak speed = 1.875 x mean
        n = max(1, int(round(duration / self.dt)))
        s = min_jerk(np.linspace(1.0 / n, 1.0, n))[:, None]
        self._run(q0 + s * (q_goal - q0))

    def move_pose(self, T_goal, straight: bool = False, min_time: float = 0.3) -> None:
        """Go to a TCP pose: a joint-space min-jerk move, or a straight Cartesian line when `straight`."""
        if not straight:
            # Free moves stay on the home configuration's branch (elbow up, wrist over the table): the branch
            # nearest the current joints can be a contorted one that sweeps the arm through the scene.
            reference = np.asarray(self.world.variant.home, dtype=float)
            reference[5] = self.q_cmd[5]
            self.move_joints(self.kin.ik(T_goal, reference), min_time)
            return
        T0 = self.kin.fk(self.q_cmd)
        dist = float(np.linalg.norm(T_goal[:3, 3] - T0[:3, 3]))
        duration = max(min_time, 1.875 * dist / self.speed)
        n = max(1, int(round(duration / self.dt)))
        qs = np.empty((n, 6))
        q = self.q_cmd
        for i, s in enumerate(min_jerk(np.linspace(1.0 / n, 1.0, n))):
            T = T_goal.copy()  # orientation is held at the goal's; only position is interpolated
            T[:3, 3] = T0[:3, 3] + s * (T_goal[:3, 3] - T0[:3, 3])
            q = self.kin.ik(T, q)
            qs[i] = q
        self._run(qs)

    def gripper(self, closing: float, seconds: float = 0.5) -> None:
        self.world.set_gripper(closing)
        self.hold(seconds)

    def hold(self, seconds: float) -> None:
        n = max(1, int(round(seconds / self.dt)))
        self._run(np.repeat(self.q_cmd[None], n, axis=0))

    # -- composite moves used by several oracles -------------------------------------------------------
    def pick(self, pos, yaw: float, approach: float = 0.12, depth: float = 0.0) -> None:
        """Top-down pick at `pos` (grasp centre), lifting back to the approach height."""
        yaw = self.best_yaw(yaw)
        grasp = np.asarray(pos, dtype=float) + [0.0, 0.0, -depth]
        self.gripper(0.0, 0.05)
        self.move_pose(top_down(grasp + [0, 0, approach], yaw))
        self.move_pose(top_down(grasp, yaw), straight=True)
        self.gripper(1.0, 0.6)
        self.move_pose(top_down(grasp + [0, 0, approach], yaw), straight=True)

    def place(self, pos, yaw: float, approach: float = 0.12) -> None:
        """Lower what the gripper holds to `pos` (TCP position), release, and retreat upwards."""
        yaw = self.best_yaw(yaw)
        pos = np.asarray(pos, dtype=float)
        self.move_pose(top_down(pos + [0, 0, approach], yaw))
        self.move_pose(top_down(pos, yaw), straight=True)
        self.gripper(0.0, 0.5)
        self.move_pose(top_down(pos + [0, 0, approach], yaw), straight=True)

    def home(self) -> None:
        self.move_joints(np.asarray(self.world.variant.home))
