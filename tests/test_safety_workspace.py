"""safety.workspace and safety.fastfk: the cheap FK, target projection and the braking bound's soundness."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sim_hands import gripper_at, pad_corners_in_tcp

from safety.fastfk import FastKinematics
from safety.limits import GRIPPER_POINTS_2F85, default_limits, load_limits
from safety.workspace import Workspace

warnings.simplefilter("ignore", UserWarning)
N = int(os.environ.get("SUDD_SAFETY_EXAMPLES", "200"))
PROPS = settings(max_examples=N, deadline=None, suppress_health_check=[HealthCheck.too_slow])
HOME = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
KEEPOUT = (0.05, 0.30, 0.0, 0.30, 0.55, 0.20)


def _ws(variant="ur5e", keepout=False):
    from sim.robot import TCP_OFFSET_Z, get_variant

    limits = default_limits(variant) if not keepout else load_limits(
        None, variant, {"workspace.keepout": [list(KEEPOUT)]})
    fk = FastKinematics(get_variant(variant), TCP_OFFSET_Z)
    return limits, fk, Workspace(limits.workspace, fk)


@pytest.mark.parametrize("variant", ["ur5e", "ur5"])
def test_fast_fk_matches_sim_kinematics(variant):
    from sim.kinematics import Kinematics
    from sim.robot import TCP_OFFSET_Z

    _, fk, _ = _ws(variant)
    kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    for q in np.random.default_rng(0).uniform(-2 * np.pi, 2 * np.pi, (300, 6)):
        T = kin.fk(q)
        px, py, pz, R = fk.pose(q.tolist())
        assert np.abs(T[:3, 3] - (px, py, pz)).max() < 1e-12
        assert np.abs(T[:3, :3] - np.reshape(R, (3, 3))).max() < 1e-12
        P, _, axes, origins = fk.frames(q.tolist())
        J = np.array([np.cross(a, np.subtract(P, o)) for a, o in zip(axes, origins)]).T
        np.testing.assert_allclose(J, kin.jacobian(q)[:3], atol=1e-12)
        np.testing.assert_allclose(np.array(axes).T, kin.jacobian(q)[3:], atol=1e-12)
        for i, (a, o) in enumerate(zip(axes, origins)):  # the Lipschitz constants bound the distances
            assert np.linalg.norm(np.cross(a, np.subtract(P, o))) <= fk.axis_reach[i] + 1e-12


def test_newton_ik_stays_on_the_seed_branch():
    """Newton from the seed lands on the analytic IK solution nearest the seed (the same branch)."""
    from sim.kinematics import Kinematics
    from sim.robot import TCP_OFFSET_Z

    _, fk, _ = _ws()
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    rng = np.random.default_rng(1)
    solved = 0
    for q in rng.uniform(-3, 3, (300, 6)):
        P, R, axes, origins = fk.frames(q.tolist())
        wrist = np.subtract(origins[4], origins[0])
        if min(abs(np.sin(q[2])), abs(np.sin(q[4])), abs(np.hypot(wrist[0], wrist[1]) - fk.d4)) < 0.2:
            continue  # near the elbow, wrist or shoulder singularity
        p2 = tuple(np.add(P, rng.normal(0, 0.01, 3)))
        sol = fk.solve(p2, R, q)
        if sol is None:
            continue
        solved += 1
        px, py, pz, R2 = fk.pose(sol)
        assert np.abs(np.subtract((px, py, pz), p2)).max() < 1e-9 and np.abs(np.subtract(R2, R)).max() < 1e-9
        T = np.eye(4)
        T[:3, :3] = np.reshape(R, (3, 3))
        T[:3, 3] = p2
        np.testing.assert_allclose(sol, kin.ik(T, q), atol=1e-6)
    assert solved > 60


def test_gripper_points_bound_the_2f85_fingers():
    """The default finger points reach at least as low (along the approach axis) as any finger collision
    geom of the MuJoCo 2F-85, open or closed, and as wide as the pads."""
    pts = np.array(GRIPPER_POINTS_2F85)
    for closing in (0.0, 255.0):
        model, data, _ = gripper_at(closing, HOME)
        deepest = -np.inf
        for local in pad_corners_in_tcp(model, data):
            deepest = max(deepest, local[:, 2].max())
            assert np.abs(local[:, 0]).max() <= np.abs(pts[:, 0]).max() + 1e-3
        assert deepest <= pts[:, 2].max() + 1e-4, (closing, deepest)


@PROPS
@given(st.integers(0, 2**32 - 1), st.booleans(), st.floats(0.0, 1.0))
def test_braking_bound_is_sound(seed, keepout, closure):
    """Whenever braking_ok accepts a joint travel box, no configuration in the box violates the region (with
    the finger points placed for any closure: the reach bounds cover them all)."""
    _, fk, ws = _ws(keepout=keepout)
    ws.set_closure(closure)
    rng = np.random.default_rng(seed)
    q = HOME + rng.normal(0, 0.6, 6)
    px, py, pz, R = fk.pose(q.tolist())
    pts = ws.points((px, py, pz), R)
    if ws.min_slack(pts) <= 0.0:
        return
    cons = ws.constraints(pts)
    scale = 10.0 ** rng.uniform(-4, -0.5)
    dlo = -np.abs(rng.normal(0, scale, 6)) * (rng.random(6) < 0.5)
    dhi = np.abs(rng.normal(0, scale, 6)) * (rng.random(6) < 0.7)
    if not ws.braking_ok(fk.frames(q.tolist()), pts, cons, list(dlo), list(dhi)):
        return
    corners = np.array([[lo if (m >> i) & 1 else hi for i, (lo, hi) in enumerate(zip(dlo, dhi))]
                        for m in range(64)])
    for d in np.vstack([corners, rng.uniform(dlo, dhi, (200, 6))]):
        x, y, z, R2 = fk.pose((q + d).tolist())
        for k, axis, sign, bound in cons:
            P = ws.points((x, y, z), R2)[k]
            assert sign * P[axis] <= bound + 1e-12


def _bins_ws():
    """(fk, workspace) with three bins' floors and walls as keep-out boxes, laid out as the sim's pick_place cell."""
    from safety.bench import bin_keepout
    from sim.robot import TCP_OFFSET_Z, get_variant

    boxes = [box for cx in (-0.24, 0.0, 0.24) for box in bin_keepout(cx, 0.557, 0.723, 0.0)]
    limits = load_limits(None, "ur5e", {"workspace.keepout": boxes})
    fk = FastKinematics(get_variant("ur5e"), TCP_OFFSET_Z)
    return fk, Workspace(limits.workspace, fk)


@PROPS
@given(st.integers(0, 2**32 - 1))
def test_far_keepout_boxes_are_left_out_without_changing_a_verdict(seed):
    """min_slack is the brute minimum over the boxes, and culling boxes farther than the braking check's travel
    (constraints(far=...)) changes no verdict."""
    from safety.workspace import _hull_separation

    fk, ws = _bins_ws()
    rng = np.random.default_rng(seed)
    q = HOME + rng.normal(0, 0.8, 6)
    px, py, pz, R = fk.pose(q.tolist())
    pts = ws.points((px, py, pz), R)
    no_boxes = Workspace(default_limits("ur5e").workspace, fk)
    brute = min([no_boxes.min_slack(pts)] + [_hull_separation(b, pts) for b in ws.keepout])
    assert ws.min_slack(pts) == brute
    if ws.min_slack(pts) <= 0.0:
        return
    scale = 10.0 ** rng.uniform(-4, -0.5)
    dlo = list(-np.abs(rng.normal(0, scale, 6)))
    dhi = list(np.abs(rng.normal(0, scale, 6)))
    travel = sum(r * max(h, -lo) for r, lo, h in zip(ws.reach_max, dlo, dhi))
    full, culled = ws.constraints(pts), ws.constraints(pts, far=travel)
    assert len(culled) <= len(full)
    frames = fk.frames(q.tolist())
    assert ws.braking_ok(frames, pts, full, dlo, dhi) == ws.braking_ok(frames, pts, culled, dlo, dhi)


def test_far_keepout_boxes_are_culled_at_home():
    fk, ws = _bins_ws()
    px, py, pz, R = fk.pose(HOME.tolist())
    pts = ws.points((px, py, pz), R)
    per_box = len(pts)
    assert len(ws.constraints(pts)) - len(ws.constraints(pts, far=0.05)) >= 10 * per_box  # most bins are far


def test_projection_keeps_orientation_and_lands_inside():
    _, fk, ws = _ws(keepout=True)
    rng = np.random.default_rng(3)
    ref = ws.points(*(lambda p: (p[:3], p[3]))(fk.pose(HOME.tolist())))
    for _ in range(300):
        q = HOME + rng.normal(0, 0.8, 6)
        px, py, pz, R = fk.pose(q.tolist())
        p = (px + rng.normal(0, 0.5), py + rng.normal(0, 0.5), pz + rng.normal(0, 0.5))
        p2 = ws.project(p, R, ref)
        if p2 is None:
            continue
        assert ws.min_slack(ws.points(p2, R)) >= ws.margin - 1e-8
        if ws.target_ok(ws.points(p, R)):
            assert np.allclose(p2, p)


def test_projection_slides_along_the_table():
    """A target below the table keeps its x, y: only z moves (the arm slides, it does not freeze)."""
    _, fk, ws = _ws()
    px, py, pz, R = fk.pose(HOME.tolist())
    ref = ws.points((px, py, pz), R)
    for x in np.linspace(-0.3, 0.3, 7):
        p2 = ws.project((x, py, -0.2), R, ref)
        assert p2[0] == pytest.approx(x) and p2[1] == pytest.approx(py)
        zs = [P[2] for P in ws.points(p2, R)]
        assert min(zs) == pytest.approx(ws.zt + ws.margin, abs=1e-8)


def test_keepout_projection_uses_the_side_the_arm_is_on():
    _, fk, ws = _ws(keepout=True)
    b = KEEPOUT
    _, _, _, R = fk.pose(HOME.tolist())
    inside = ((b[0] + b[3]) / 2 + 0.04, (b[1] + b[4]) / 2, 0.1)  # nearer the +x face
    above = ws.points(((b[0] + b[3]) / 2, (b[1] + b[4]) / 2, 0.4), R)
    p2 = ws.project(inside, R, above)
    assert p2[2] > b[5] and p2[0] == pytest.approx(inside[0])  # pushed up, towards where the arm is


def test_a_thin_wall_between_the_fingertips_is_a_hit_and_the_target_is_pushed_to_one_side():
    """Every point outside a bin wall 8 mm thick that passes between TCP and a fingertip is still a hit: the
    gripper is the hull of its points, which project moves wholly to the side the arm came from."""
    from sim.robot import TCP_OFFSET_Z, get_variant

    fk = FastKinematics(get_variant("ur5e"), TCP_OFFSET_Z)
    p, R = (0.1, 0.5, 0.2), (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)  # pointing down, fingers along x
    wall = (0.122, 0.3, 0.0, 0.130, 0.7, 0.3)  # above the TCP, between the TCP (x 0.1) and the fingertips at x 0.152
    limits = load_limits(None, "ur5e", {"workspace.keepout": [list(wall)]})
    ws, free = Workspace(limits.workspace, fk), Workspace(default_limits("ur5e").workspace, fk)
    pts = ws.points(p, R)
    outside = [max(wall[0] - P[0], P[0] - wall[3], wall[1] - P[1], P[1] - wall[4], wall[2] - P[2], P[2] - wall[5])
               for P in pts]
    assert min(outside) > 0.01  # every point alone is clear of the wall ...
    assert free.min_slack(pts) > 0.01 and ws.min_slack(pts) < -0.02  # ... the gripper is not
    left = ws.points((0.0, 0.5, 0.2), R)  # the arm came from the -x side: the whole gripper stays there
    fixed = ws.project(p, R, left)
    assert fixed is not None and ws.target_ok(ws.points(fixed, R), 1e-9)
    assert max(P[0] for P in ws.points(fixed, R)) <= wall[0] - ws.margin + 1e-9
    (face,) = {c[1:] for c in ws.constraints(pts, left)[6 + len(pts):]}  # one face of the wall for all points
    assert face == (0, 1.0, wall[0])
