"""The finger points follow the fingers' closure: the 2F-85's closed points bound its pads at every closure, a
half-closed hand reaches under a box's edge that open fingers cannot, opening is held where the open fingers
would reach into a box, and the limits file says what is wrong with a bad set of closed points."""

from __future__ import annotations

import math

import numpy as np
import pytest
from safety_filter_streams import HOME, make_filter
from sim_hands import gripper_at, pad_corners_in_tcp, pad_geoms

from safety.fastfk import FastKinematics
from safety.limits import default_limits, load_limits
from safety.workspace import Workspace
from sim.config import ConfigError

IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def _ws(limits=None):
    from sim.robot import TCP_OFFSET_Z, get_variant

    limits = limits or default_limits("ur5e")
    return Workspace(limits.workspace, FastKinematics(get_variant("ur5e"), TCP_OFFSET_Z))


def _local_points(ws) -> np.ndarray:
    return np.array(ws.points((0.0, 0.0, 0.0), IDENTITY)[1:])


def test_the_points_bound_the_2f85_pads_at_every_closure():
    """At each tenth of the stroke, the points placed for the measured closure reach as wide across the gap as
    the MuJoCo 2F-85's pads and as deep along the approach."""
    ws = _ws()
    closures = []
    for ctrl in np.linspace(0.0, 255.0, 11):
        model, data, closure = gripper_at(ctrl, HOME)
        closures.append(closure)
        ws.set_closure(closure)
        pts = _local_points(ws)
        for local in pad_corners_in_tcp(model, data):
            assert np.abs(local[:, 0]).max() <= np.abs(pts[:, 0]).max() + 1e-4, (closure, local[:, 0])
            assert local[:, 2].max() <= pts[:, 2].max() + 1e-4
    assert closures[0] < 0.01 and closures[-1] > 0.95  # the whole stroke was covered


def test_the_collision_guard_places_the_fingers_where_the_2f85_has_them():
    """The guard's pads, placed for a measured closure, lie within a millimetre of the simulated gripper's
    (in the wrist's frame), and a closed hand is farther from a box beside the open fingers."""
    from safety.collision import CollisionGuard

    guard = CollisionGuard(default_limits("ur5e"))
    gm, gd = guard.model, guard.data
    for ctrl in (0.0, 64.0, 128.0, 192.0, 255.0):
        model, data, closure = gripper_at(ctrl, HOME)
        guard.set_closure(closure)
        guard.clearance(HOME)
        for g in pad_geoms(model):
            name = model.body(model.geom_bodyid[g]).name
            w_sim, w_guard = model.body("wrist_3_link").id, gm.body("wrist_3_link").id
            local_sim = data.xmat[w_sim].reshape(3, 3).T @ (data.xpos[model.body(name).id] - data.xpos[w_sim])
            local_guard = gd.xmat[w_guard].reshape(3, 3).T @ (gd.xpos[gm.body(name).id] - gd.xpos[w_guard])
            assert np.abs(local_sim - local_guard).max() < 1e-3, (ctrl, name)
    guard.set_closure(0.0)
    guard.clearance(HOME)
    left, right = (gd.xpos[gm.body(f"gripper/{side}_pad").id].copy() for side in ("left", "right"))
    centre = left + 0.025 * (left - right) / np.linalg.norm(left - right)  # 2.5 cm beyond the open left pad
    beside = CollisionGuard(load_limits(None, "ur5e", {"workspace.keepout": [[*(centre - 0.004), *(centre + 0.004)]]}))
    near_open = beside.clearance(HOME)[0]
    beside.set_closure(1.0)
    assert near_open < 0.025 and beside.clearance(HOME)[0] > near_open + 0.01


def test_closure_places_the_points_and_anything_else_counts_as_open():
    ws = _ws()
    assert np.abs(_local_points(ws)[:, 0]).max() == pytest.approx(0.052)  # open until told
    assert ws.set_closure(0.5) and np.abs(_local_points(ws)[:, 0]).max() == pytest.approx(0.031)
    assert not ws.set_closure(0.5)  # unchanged
    ws.set_closure(3.0)
    assert ws.closure == 1.0 and np.abs(_local_points(ws)[:, 0]).max() == pytest.approx(0.010)
    for bad in (math.nan, math.inf, None, "half"):
        ws.set_closure(0.7)
        ws.set_closure(bad)
        assert ws.closure == 0.0 and np.abs(_local_points(ws)[:, 0]).max() == pytest.approx(0.052), bad
    never = _ws(load_limits(None, "ur5e", {"workspace.gripper_points_closed": []}))
    never.set_closure(1.0)
    assert np.abs(_local_points(never)[:, 0]).max() == pytest.approx(0.052)  # [] : the open points always


def test_bad_closed_points_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"gripper_points_closed has 2 points, gripper_points 4"):
        load_limits(None, "ur5e", {"workspace.gripper_points_closed": [[0.01, 0.0, 0.018]] * 2})
    with pytest.raises(ConfigError, match=r"gripper_points_closed\[1\] = \[0.01, 0.0, 0.9\]: each coordinate"):
        load_limits(None, "ur5e", {"workspace.gripper_points_closed": [[0.01, 0.0, 0.018], [0.01, 0.0, 0.9],
                                                                       [0.01, 0.0, 0.018], [0.01, 0.0, 0.018]]})


# ---- the filter: under a box's edge -----------------------------------------------------------------------
def _under_an_edge():
    """A filter whose keep-out box is a slab 1 cm above a spot 4 cm from the TCP across the finger gap (as a
    cabinet's top is above its handle), and joint targets: above the slab (start), beside its edge (the finger
    points at its height) and under it."""
    from safety.filter import SafetyFilter

    fk = make_filter("ur5e").fk
    px, py, pz, R = fk.pose(list(HOME))
    x_axis = np.array(R[0::3])  # the TCP's x: across the finger gap
    assert abs(abs(x_axis[1]) - 1.0) < 1e-6 or abs(abs(x_axis[0]) - 1.0) < 1e-6
    ax = int(np.argmax(np.abs(x_axis)))
    spot = np.array([px, py, 0.13])
    lo, hi = spot - 0.10, spot + 0.10
    near = spot[ax] + 0.040 * np.sign(x_axis[ax])  # the slab's near face, 4 cm along +x
    if x_axis[ax] > 0:
        lo[ax], hi[ax] = near, near + 0.2
    else:
        lo[ax], hi[ax] = near - 0.2, near
    lo[2], hi[2] = 0.14, 0.15
    limits = load_limits(None, "ur5e", {"workspace.keepout": [[*lo, *hi]]})
    filt = SafetyFilter(limits, collision=False)
    above = fk.solve((spot[0], spot[1], 0.22), R, list(HOME))
    beside = fk.solve((spot[0], spot[1], 0.155), R, above)
    under = fk.solve(tuple(spot), R, beside)
    return filt, np.array(above), np.array(beside), np.array(under)


def _drive(filt, q, target, cycles=1500, t0=0.0):
    for k in range(cycles):
        t = t0 + k * filt.dt
        q = filt.step(target, q, None, t, t).q
    return q


@pytest.mark.parametrize("closure, reaches", [(0.0, False), (0.5, True)])
def test_half_closed_fingers_reach_under_an_edge_that_open_ones_cannot(closure, reaches):
    filt, above, _, under = _under_an_edge()
    q = _drive(filt, above, above, 300)
    filt.set_finger_closure(closure)
    q = _drive(filt, q, under, 2000, t0=1.0)
    z = filt.fk.pose(list(q))[2]
    if reaches:
        assert z == pytest.approx(0.13, abs=1e-3)
    else:  # held with the open finger points (1.8 cm below the TCP) above the slab's top at 0.15
        assert 0.168 - 1e-9 <= z <= 0.175
    pts, slack = filt.workspace.at(filt.fk.pose(list(q)))
    assert slack >= 0.0


def test_opening_is_allowed_only_where_the_open_points_clear_the_boxes():
    filt, above, beside, under = _under_an_edge()
    q = _drive(filt, above, above, 300)
    assert filt.fingers_may_open(0.0)  # above the slab: open is fine
    filt.set_finger_closure(0.5)
    q = _drive(filt, q, beside, 1500, t0=1.0)
    assert filt.fk.pose(list(q))[2] == pytest.approx(0.155, abs=1e-3)
    assert not filt.fingers_may_open(0.0)  # beside its edge the open fingers would reach into it
    assert filt.fingers_may_open(0.45)  # a little wider still clears it
    assert filt.fingers_may_open(1.0)  # closing: always
    q = _drive(filt, q, under, 1500, t0=4.0)
    assert filt.fingers_may_open(0.0)  # under it, the open fingers stay below its bottom
