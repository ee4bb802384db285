"""The command streams and set-up shared by the safety.filter tests (test_safety_filter_*.py).

Each example runs a stream through a SafetyFilter with a simulated arm (ideal integrator, measured joints
one cycle behind, safety.harness) and checks the commanded stream the robot would receive.

Tolerance (safety.harness): a limit holds when value <= limit * (1 + 1e-9) + the round-off floor of the n-th
finite difference of positions, 4 eps max(1, |q|) (2 / dt)^n (~6e-6 rad/s^3 on the jerk at 500 Hz);
Cartesian limits hold to 1e-9 m.

Examples: SUDD_SAFETY_EXAMPLES (default 200) for the main invariant property (MAIN), a quarter of it (at
least 25) for the others (SIDE); deadline off (the first example pays the imports).
"""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from safety.filter import SafetyFilter
from safety.harness import Command
from safety.limits import default_limits, load_limits

warnings.simplefilter("ignore", UserWarning)

N_MAIN = int(os.environ.get("SUDD_SAFETY_EXAMPLES", "200"))
N_SIDE = max(25, N_MAIN // 4)
_HC = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
MAIN = settings(max_examples=N_MAIN, deadline=None, suppress_health_check=_HC)
SIDE = settings(max_examples=N_SIDE, deadline=None, suppress_health_check=_HC)

HOME = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def _low(variant: str) -> np.ndarray:
    """Gripper pointing down, TCP 4.5 cm above the table (finger points ~2.4 cm above it)."""
    from sim.kinematics import Kinematics
    from sim.robot import TCP_OFFSET_Z

    kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    T = kin.fk(HOME)
    T[:3, 3] = (-0.2, 0.45, 0.045)
    return kin.ik(T, HOME)


STARTS = {
    "home": {"ur5e": HOME, "ur5": HOME},
    "low": {"ur5e": _low("ur5e"), "ur5": _low("ur5")},
    "wrist_limit": {v: np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 2 * math.pi - 0.2])
                    for v in ("ur5e", "ur5")},
    "elbow_limit": {v: np.array([-1.384, -2.929, 2.95, -2.964, -1.571, 0.09]) for v in ("ur5e", "ur5")},
}


def start_pose(name: str, start: str) -> np.ndarray:
    """The joint angles of start pose `start` on the variant of limits `name`."""
    return STARTS[start][LIMITS[name].variant]


KEEPOUT = (0.05, 0.30, 0.0, 0.30, 0.55, 0.20)  # a box on the table in front of the robot


def _limits(name: str):
    if name == "keepout":
        return load_limits(None, "ur5e", {"workspace.keepout": [list(KEEPOUT)],
                                          "workspace.box_min": [-0.6, 0.05, 0.0],
                                          "workspace.box_max": [0.6, 0.8, 0.7]})
    return default_limits(name)


LIMITS = {name: _limits(name) for name in ("ur5e", "ur5", "keepout")}


def make_filter(name: str, **kw) -> SafetyFilter:
    """A SafetyFilter on limits `name`, collision guard off unless given."""
    return SafetyFilter(LIMITS[name], collision=kw.pop("collision", False), **kw)


def inside(filt, q, margin: float = 0.0) -> bool:
    """q is strictly inside the soft joint limits, and more than `margin` (m) inside the workspace."""
    j = filt.limits.joints
    if np.any(q <= np.array(j.soft_lower)) or np.any(q >= np.array(j.soft_upper)):
        return False
    px, py, pz, R = filt.fk.pose(list(q))
    return filt.workspace.min_slack(filt.workspace.points((px, py, pz), R)) > margin


SEGMENTS = ("random", "jump", "huge", "nan", "shape", "tcp", "below_table", "keepout", "oscillate", "stale",
            "backwards", "future", "smooth", "hold")


@st.composite
def streams(draw, max_segments: int = 4, max_len: int = 120):
    """(limits name, start pose name, seed, segments) of an adversarial stream made of segments."""
    name = draw(st.sampled_from(sorted(LIMITS)))
    start = draw(st.sampled_from(sorted(STARTS)))
    seed = draw(st.integers(0, 2**32 - 1))
    segs = draw(st.lists(st.tuples(st.sampled_from(SEGMENTS), st.integers(1, max_len), st.floats(0.001, 1.0)),
                         min_size=1, max_size=max_segments))
    return name, start, seed, segs


def commands(filt, q0, seed, segs, max_age):
    """Commands of the segments; command_time is the clock unless the segment plays with it."""
    rng = np.random.default_rng(seed)
    dt = filt.dt
    cmds = []
    tgt = q0.copy()
    fk = filt.fk
    for kind, n, x in segs:
        for k in range(n):
            now = len(cmds) * dt
            ct = now
            q = tgt
            tcp = None
            if kind == "random":
                q = q0 + rng.normal(0.0, 2.0 * x, 6)
            elif kind == "jump":
                if k == 0:
                    tgt = q0 + rng.uniform(-8.0, 8.0, 6) * x
                q = tgt
            elif kind == "huge":
                q = rng.choice([-1.0, 1.0], 6) * 10.0 ** rng.uniform(1, 12, 6)
            elif kind == "nan":
                q = tgt.copy()
                q[rng.integers(6)] = rng.choice([np.nan, np.inf, -np.inf])
            elif kind == "shape":
                q = rng.choice(np.array([None, "text", [1.0] * 5, [[0.0] * 6], [0.0] * 7], dtype=object))
            elif kind == "tcp":
                px, py, pz, R = fk.pose(list(q0))
                T = np.eye(4)
                T[:3, :3] = np.reshape(R, (3, 3))
                T[:3, 3] = (px, py, pz) + rng.normal(0.0, 0.6 * x, 3)
                if rng.random() < 0.2:
                    T[:3, :3] *= 1.0 + rng.uniform(0.01, 0.5)  # not a rotation
                q, tcp = None, T
            elif kind == "below_table":
                q = q0.copy()
                q[1] += 1.2 * x
                q[2] += rng.uniform(-0.5, 0.5) * x
            elif kind == "keepout":
                px, py, pz, R = fk.pose(list(q0))
                target = np.array([rng.uniform(KEEPOUT[0], KEEPOUT[3]), rng.uniform(KEEPOUT[1], KEEPOUT[4]),
                                   rng.uniform(0.02, KEEPOUT[5])])
                T = np.eye(4)
                T[:3, :3] = np.reshape(R, (3, 3))
                T[:3, 3] = target
                q, tcp = None, T
            elif kind == "oscillate":
                q = tgt + (x if k % 2 else -x) * 0.2
            elif kind == "stale":
                ct = now - max_age * (1.0 + 5.0 * x)
            elif kind == "backwards":
                ct = now - (k + 1) * dt * 3.0
            elif kind == "future":
                ct = now + 0.2 + x
            elif kind == "smooth":
                q = tgt + 0.2 * x * np.sin(np.arange(6) + k * dt * 4.0)
            cmds.append(Command(q=q, command_time=ct, tcp=tcp))
    return cmds
