"""The grasp's axis as two more aux targets (`aux_grasp_axis`): which way the fingers must close, relative to
the gripper's own yaw.

Why: the aux head regressed the grasp and release points only, so nothing taught the image encoder an
object's orientation, and the shipped policy closes on bars along their length (the evaluation's `closes`:
9 of the 11 bars it never lifted were closed 38-90 degrees off the grasp yaw, every time). A bar is wider
(9 cm) than the 2F-85 opens (8.5 cm).

The label is (cos 2d, sin 2d), d = grasp yaw - TCP yaw: the doubled angle because a half turn of the
gripper closes the same way, so a unit vector that says "turn by d" without the half-turn ambiguity. Only an
object whose footprint repeats every half turn (a bar) has one axis to name; a square block's grasps repeat
every quarter turn and a cylinder's at every yaw, and over their equally good grasps (cos 2d, sin 2d)
averages to (0, 0), which is their label: no axis preferred, and what a regression on them would learn anyway.

numpy only, like policy.action_frame: the labels of the recorded episodes and of the rendered views alike.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sim.tasks.pick_place import footprint_period


def yaw_of(rot6d: np.ndarray) -> np.ndarray:
    """(..., 6) rot6d of a top-down pose -> (...,) the yaw of its x axis, along which the fingers close."""
    r = np.asarray(rot6d, np.float64)
    return np.arctan2(r[..., 1], r[..., 0])


def has_axis(obj) -> bool:
    """Whether an object (shape, size) has one grasp axis up to a half turn (see the module doc)."""
    return period_has_axis(footprint_period(obj) or 0.0)


def period_has_axis(period) -> np.ndarray:
    """The same from a footprint period (sim.tasks.pick_place.footprint_period; 0 for a round footprint)."""
    return np.asarray(period) > np.pi * 0.75


def axis_label(grasp_yaw, tcp_yaw, axis: bool | np.ndarray) -> np.ndarray:
    """(..., 2) float32: (cos 2d, sin 2d) of d = grasp_yaw - tcp_yaw where `axis`, else (0, 0)."""
    d = 2.0 * (np.asarray(grasp_yaw, np.float64) - np.asarray(tcp_yaw, np.float64))
    label = np.stack([np.cos(d), np.sin(d)], axis=-1)
    return (label * np.asarray(axis, np.float64)[..., None]).astype(np.float32)


# the task_record param naming the object an episode picks up, per family that picks one up
PICKED = {"pick_place": "target", "drawer_put": "target", "stack": "top"}


def episode_target_has_axis(meta: dict) -> bool:
    """Whether a recorded episode's picked-up object (its task_record) has a grasp axis. A family that picks
    up no object (drawer_open, drawer_close: the handle is part of the cabinet) has none: label (0, 0)."""
    record = meta.get("task_record") or {}
    task = record.get("family", meta.get("task"))
    if task is not None and task not in PICKED:
        return False
    target = (record.get("params") or {}).get(PICKED.get(task, "target"))
    for o in record.get("objects", ()):
        if o.get("name") == target:
            return has_axis(SimpleNamespace(shape=o["shape"], size=o["size"]))
    raise ValueError(f"episode seed {meta.get('seed')}: its task_record names no picked-up object with a shape, so "
                     "no grasp-axis label; aux_grasp_axis needs data recorded with task records")


def angle_error_deg(pred: np.ndarray, want: np.ndarray) -> np.ndarray:
    """(N, 2) predicted and true labels -> (N,) how far the predicted grasp yaw is off, in degrees (0-90)."""
    a = np.arctan2(pred[..., 1], pred[..., 0]) - np.arctan2(want[..., 1], want[..., 0])
    return np.degrees(np.abs((a + np.pi) % (2 * np.pi) - np.pi) / 2.0)


def turn_label(grasp_yaw, tcp_yaw, period) -> np.ndarray:
    """(..., 2) float32: (cos k d, sin k d), k = 2 pi / period, d = grasp_yaw - tcp_yaw: the wrist turn to the
    nearest equally good grasp, without the ambiguity of the footprint's symmetry. Unlike `axis_label`, a square
    block (period a quarter turn) has one: k = 4. A bar (half a turn) gets axis_label's own; a round footprint
    (period 0) (0, 0). Taught to the turn locator (policy/turn_query.py)."""
    p = np.asarray(period, np.float64)
    k = np.where(p > 0, 2.0 * np.pi / np.where(p > 0, p, 1.0), 0.0)
    d = k * (np.asarray(grasp_yaw, np.float64) - np.asarray(tcp_yaw, np.float64))
    return (np.stack([np.cos(d), np.sin(d)], axis=-1) * (p > 0)[..., None]).astype(np.float32)


def wrap(angle: float, period: float) -> float:
    """`angle` [rad] to its equivalent in [-period/2, period/2): the nearest of the turns a footprint of `period`
    makes equal."""
    return float((angle + period / 2) % period - period / 2)


def turn_of(label, period: float) -> float:
    """The wrist turn [rad] in (-period/2, period/2] a `turn_label` (cos, sin) says, for a footprint of `period`."""
    c, s = (float(v) for v in np.asarray(label, np.float64).reshape(2))
    return float(np.arctan2(s, c)) * period / (2.0 * np.pi)
