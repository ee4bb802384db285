"""safety.filter: scenario checks of the target shaping — TCP targets in every form, sliding along the table and
over a keep-out box, stopping at a joint limit, scaling that keeps the direction, leaving a violated region.
Set-up: safety_filter_streams.
"""

from __future__ import annotations

import numpy as np
from safety_filter_streams import HOME, KEEPOUT, LIMITS, make_filter, start_pose

from safety.harness import Command, check_stream, run_stream, tcp_speeds


def test_tcp_targets_in_every_form_are_followed():
    filt = make_filter("ur5e")
    px, py, pz, R = filt.fk.pose(list(HOME))
    T = np.eye(4)
    T[:3, :3] = np.reshape(R, (3, 3))
    T[:3, 3] = (px + 0.05, py, pz)
    from sim.rotations import matrix_to_rotvec

    rv = matrix_to_rotvec(T[:3, :3])
    import mujoco

    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, T[:3, :3].flatten())
    for form in (T, np.concatenate([T[:3, 3], rv]), np.concatenate([T[:3, 3], quat])):
        filt = make_filter("ur5e")
        q = HOME
        for k in range(1500):
            r = filt.step(None, q, None, k * filt.dt, k * filt.dt, desired_tcp=form)
            q = r.q
        p = filt.fk.pose(list(q))
        assert abs(p[0] - (px + 0.05)) < 1e-6 and abs(p[1] - py) < 1e-6 and abs(p[2] - pz) < 1e-6


def _cartesian_path(filt, q0, waypoints, speed):
    """Joint commands along straight TCP lines through waypoints (orientation of q0) at `speed`."""
    px, py, pz, R = filt.fk.pose(list(q0))
    p = np.array([px, py, pz])
    q = q0.copy()
    cmds = []
    for w in waypoints:
        w = np.asarray(w, float)
        n = max(1, int(np.linalg.norm(w - p) / speed / filt.dt))
        for s in np.linspace(0, 1, n + 1)[1:]:
            x = p + s * (w - p)
            sol = filt.fk.solve(tuple(x), R, q)
            assert sol is not None
            q = np.array(sol)
            cmds.append(q)
        p = w
    return cmds


def test_table_slide_descends_onto_the_plane_and_slides():
    """A TCP path through the table: the arm stops at the finger clearance and slides along it at speed."""
    filt = make_filter("ur5e")
    px, py, pz, _ = filt.fk.pose(list(HOME))
    qs = _cartesian_path(filt, HOME, [(px, py, -0.05), (px + 0.3, py, -0.05), (px - 0.2, py, -0.05)], 0.1)
    qs += [qs[-1]] * 500
    res = run_stream(filt, HOME, [Command(q=q, command_time=k * filt.dt) for k, q in enumerate(qs)])
    assert not check_stream(res.q, filt.dt, filt.limits, filt.fk, filt.workspace)
    x = np.array([filt.fk.pose(list(q))[0] for q in res.q])
    z = np.array([filt.fk.pose(list(q))[2] for q in res.q])
    ws = filt.limits.workspace
    plane = ws.table_z + ws.finger_clearance + max(p[2] for p in ws.gripper_points) + ws.target_margin
    assert abs(z[-1] - plane) < 1e-6  # rests on the target plane
    assert x.max() > px + 0.3 - 1e-6 and abs(x[-1] - (px - 0.2)) < 1e-6  # slid all the way, both ways
    lin, _ = tcp_speeds(res.q, filt.dt, filt.fk)
    assert np.percentile(lin[lin > 0.01], 50) > 0.08  # sliding at ~ the commanded 0.1 m/s, not frozen


def test_keepout_box_target_slides_over_its_top_face():
    """Coming from above, a TCP path through a keep-out box is followed over its top face, then resumed."""
    filt = make_filter("keepout")
    b = KEEPOUT
    cx, cy = (b[0] + b[3]) / 2, (b[1] + b[4]) / 2
    qs = _cartesian_path(filt, HOME, [(b[0] + 0.02, cy, 0.35), (b[0] + 0.02, cy, 0.10), (b[3] + 0.12, cy, 0.10)],
                         0.1)
    qs += [qs[-1]] * 800
    res = run_stream(filt, HOME, [Command(q=q, command_time=k * filt.dt) for k, q in enumerate(qs)])
    assert not check_stream(res.q, filt.dt, filt.limits, filt.fk, filt.workspace)
    P = np.array([filt.fk.pose(list(q))[:3] for q in res.q])
    over = (P[:, 0] > b[0]) & (P[:, 0] < b[3])
    assert over.any() and P[over, 2].min() > b[5]  # over the box it stays above the top face
    np.testing.assert_allclose(P[-1], (b[3] + 0.12, cy, 0.10), atol=1e-6)  # and ends on the target
    assert any(e.kind == "workspace" for e in res.events)


def test_joint_target_beyond_limit_stops_inside():
    filt = make_filter("ur5e")
    q0 = start_pose("ur5e", "wrist_limit")
    tgt = q0.copy()
    tgt[5] = 100.0
    res = run_stream(filt, q0, [Command(q=tgt, command_time=k * filt.dt) for k in range(1500)])
    assert not check_stream(res.q, filt.dt, filt.limits)
    up = filt.limits.joints.soft_upper[5]
    assert up - 1e-6 < res.q[-1, 5] <= up
    assert any(e.kind == "joint_position" for e in res.events)


def test_direction_is_kept_when_scaling():
    """A multi-joint jump: every joint moves in proportion (common factor), velocities stay parallel."""
    filt = make_filter("ur5e")
    d = np.array([0.5, -0.3, 0.4, 0.2, -0.6, 1.0])
    res = run_stream(filt, HOME, [Command(q=HOME + d, command_time=k * filt.dt) for k in range(2000)])
    path = res.q - HOME
    s = path @ d / (d @ d)
    assert np.abs(path - np.outer(s, d)).max() < 1e-9  # on the straight joint-space line
    assert np.abs(res.q[-1] - (HOME + d)).max() == 0.0  # and exactly on target at the end


def test_started_outside_the_region_it_may_leave_but_not_go_deeper():
    """An arm that starts 2 mm below the finger clearance is never driven deeper, and can climb out."""
    from sim.kinematics import Kinematics
    from sim.robot import TCP_OFFSET_Z

    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    ws_lim = LIMITS["ur5e"].workspace
    T = kin.fk(HOME)
    T[:3, 3] = (-0.2, 0.45, ws_lim.table_z + ws_lim.finger_clearance + 0.018 - 0.002)
    q0 = kin.ik(T, HOME)

    def slack(filt, q):
        px, py, pz, R = filt.fk.pose(list(q))
        return filt.workspace.min_slack(filt.workspace.points((px, py, pz), R))

    for z, deeper in ((0.0, True), (0.1, False)):
        filt = make_filter("ur5e")
        T2 = T.copy()
        T2[2, 3] = z
        goal = kin.ik(T2, q0)
        res = run_stream(filt, q0, [Command(q=goal, command_time=k * filt.dt) for k in range(1500)])
        s0 = slack(filt, q0)
        assert s0 < 0 and min(slack(filt, q) for q in res.q) >= s0 - 1e-9
        if not deeper:
            assert slack(filt, res.q[-1]) > 0.05 and np.abs(res.q[-1] - goal).max() == 0.0
