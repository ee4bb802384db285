"""sim.kinematics: FK against the MuJoCo model, analytic IK round trips, Jacobian, rotation vectors."""

from __future__ import annotations

import warnings

import mujoco
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from sim.kinematics import (
    Kinematics,
    UnreachableError,
    matrix_to_pose,
    matrix_to_rotvec,
    pose_to_matrix,
    rotvec_to_matrix,
    wrap_angle,
)
from sim.robot import ARM_JOINTS, FLANGE_SITE, TCP_OFFSET_Z, TCP_SITE, get_variant, robot_spec

VARIANT_NAMES = ("ur5e", "ur5")


def _random_q(variant, n, seed):
    v = get_variant(variant)
    return np.random.default_rng(seed).uniform(v.joint_lower, v.joint_upper, size=(n, 6))


def _nonsingular_q(variant, n, seed):
    """Random configurations away from the wrist (sin q5 = 0) and elbow (sin q3 = 0) singularities."""
    Q = _random_q(variant, 4 * n, seed)
    keep = (np.abs(np.sin(Q[:, 4])) > 0.05) & (np.abs(np.sin(Q[:, 2])) > 0.05)
    return Q[keep][:n]


def _rot_err(Ra, Rb):
    return np.linalg.norm(matrix_to_rotvec(Ra.T @ Rb))


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_fk_matches_mujoco(variant):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        model = robot_spec(variant).compile()
    data = mujoco.MjData(model)
    adr = [model.jnt_qposadr[model.joint(j).id] for j in ARM_JOINTS]
    assert adr == list(range(6))
    flange = Kinematics(variant)
    tcp = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    Q = _random_q(variant, 200, seed=1)
    Tf, Tt = flange.fk_batch(Q), tcp.fk_batch(Q)
    for q, T_f, T_t in zip(Q, Tf, Tt):
        data.qpos[:6] = q
        mujoco.mj_forward(model, data)
        for site, T in ((FLANGE_SITE, T_f), (TCP_SITE, T_t)):
            s = data.site(site)
            assert np.linalg.norm(s.xpos - T[:3, 3]) <= 1e-6, (site, q)
            assert _rot_err(s.xmat.reshape(3, 3), T[:3, :3]) <= 1e-6, (site, q)
    # The single-configuration API agrees with the batch one.
    np.testing.assert_allclose(tcp.fk(Q[0]), Tt[0], atol=1e-15)
    np.testing.assert_allclose(flange.fk_flange(Q[0]), Tf[0], atol=1e-15)


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_ik_round_trip(variant):
    kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    for q in _nonsingular_q(variant, 200, seed=2):
        T = kin.fk(q)
        Q, valid = kin.ik_all(T)
        assert Q.shape == (8, 6) and valid.shape == (8,) and valid.any()
        assert np.isnan(Q[~valid]).all()
        sols = Q[valid]
        assert np.all(sols > -np.pi) and np.all(sols <= np.pi)
        err = np.abs(kin.fk_batch(sols) - T).max()
        assert err < 1e-9, (q, err)
        assert np.abs(wrap_angle(sols - q)).max(axis=1).min() < 1e-8
        np.testing.assert_allclose(kin.ik(T, q), q, atol=1e-8, rtol=0)


def test_generic_pose_has_eight_distinct_branches():
    kin = Kinematics("ur5e")
    T = kin.fk([0.3, -1.2, 1.4, -1.0, 1.1, 0.4])
    Q, valid = kin.ik_all(T)
    assert valid.all()
    diffs = np.abs(wrap_angle(Q[:, None] - Q[None])).max(axis=2)
    assert (diffs + np.eye(8) * 10).min() > 1e-3  # pairwise distinct
    # Branch bits: shoulder is bit 2, wrist is bit 1, elbow is bit 0.
    assert np.allclose(Q[0:4, 0], Q[0, 0]) and not np.isclose(Q[0, 0], Q[4, 0])
    assert np.all(np.sign(Q[[0, 2, 4, 6], 2]) == -np.sign(Q[[1, 3, 5, 7], 2]))
    assert np.all(np.sign(Q[[0, 1, 4, 5], 4]) == -np.sign(Q[[2, 3, 6, 7], 4]))


def test_ik_picks_nearest_unwrapped_equivalent():
    kin = Kinematics("ur5e")
    q = np.array([0.3, -1.2, 1.4, -1.0, 1.1, 0.4])
    q_far = q + 2 * np.pi * np.array([-1, 1, 0, 1, 0, -1])  # same pose, other turns, within limits
    sol = kin.ik(kin.fk(q), q_far + 0.01)
    np.testing.assert_allclose(sol, q_far, atol=1e-9)


def test_ik_tracks_a_continuous_path():
    kin = Kinematics.with_tcp_z("ur5", TCP_OFFSET_Z)
    q = np.array(get_variant("ur5").home)
    path = q + np.linspace(0, 1, 50)[:, None] * np.array([0.5, 0.3, -0.4, 0.6, 0.2, 3.5])
    for target in path:
        q = kin.ik(kin.fk(target), q)
        np.testing.assert_allclose(q, target, atol=1e-8)


def test_wrist_singularity_keeps_current_q6():
    kin = Kinematics("ur5e")
    q = np.array([0.2, -1.3, 1.5, -0.7, 0.0, 0.9])  # q5 = 0: axes 4 and 6 aligned
    T = kin.fk(q)
    q_cur = q + np.array([0.01, 0.01, -0.01, 0.3, 0.01, -0.3])
    sol = kin.ik(T, q_cur)
    assert np.all(np.isfinite(sol))
    assert sol[5] == pytest.approx(q_cur[5])
    assert np.abs(kin.fk(sol) - T).max() < 1e-9
    Q, valid = kin.ik_all(T, q6_hint=0.25)
    singular = valid & (np.abs(np.sin(Q[:, 4])) < 1e-9)  # the other shoulder branch is not singular
    assert singular.sum() == 4 and np.allclose(Q[singular, 5], 0.25)
    assert np.abs(kin.fk_batch(Q[valid]) - T).max() < 1e-9


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_unreachable_far_pose_says_how_far(variant):
    kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    T = pose_to_matrix([1.5, 0.3, 0.4], [np.pi, 0, 0])
    Q, valid = kin.ik_all(T)
    assert not valid.any() and np.isnan(Q).all()
    with pytest.raises(UnreachableError, match=r"1\.5\d\d m from the base.*at most 0\.8\d\d m") as info:
        kin.ik(T, get_variant(variant).home)
    assert variant in str(info.value) and "closer" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_unreachable_on_base_axis():
    kin = Kinematics("ur5e")
    with pytest.raises(UnreachableError, match="base z axis"):
        kin.ik(pose_to_matrix([0.0, 0.0, 0.5], [0, 0, 0]), np.zeros(6))


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_jacobian_matches_finite_differences(variant):
    kin = Kinematics.with_tcp_z(variant, TCP_OFFSET_Z)
    h = 1e-6
    for q in _random_q(variant, 20, seed=3):
        J = kin.jacobian(q)
        Jn = np.empty((6, 6))
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            Tp, Tm = kin.fk(q + dq), kin.fk(q - dq)
            Jn[:3, i] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            Jn[3:, i] = matrix_to_rotvec(Tp[:3, :3] @ Tm[:3, :3].T) / (2 * h)
        np.testing.assert_allclose(J, Jn, atol=1e-7)


_unit = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: 0.1 < np.linalg.norm(v))


@settings(max_examples=200, deadline=None)
@given(axis=_unit, angle=st.floats(0.0, np.pi))
@example(axis=(1.0, 0.0, 0.0), angle=np.pi)
@example(axis=(0.3, -0.5, 0.8), angle=np.pi - 1e-9)
@example(axis=(0.0, 0.0, 1.0), angle=0.0)
@example(axis=(0.3, -0.5, 0.8), angle=1e-12)
@example(axis=(0.3, -0.5, 0.8), angle=1e-7)
def test_rotvec_round_trip(axis, angle):
    rv = angle * np.asarray(axis) / np.linalg.norm(axis)
    R = rotvec_to_matrix(rv)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = matrix_to_rotvec(R)
    assert np.linalg.norm(back) <= np.pi + 1e-12
    np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-12)
    if angle < np.pi - 1e-6:
        np.testing.assert_allclose(back, rv, atol=1e-12)
    else:  # at pi, +axis and -axis are the same rotation
        assert min(np.linalg.norm(back - rv), np.linalg.norm(back + rv)) < 1e-7


def test_pose_helpers_round_trip():
    pose = np.array([0.4, -0.2, 0.3, 0.1, -2.9, 0.4])
    T = pose_to_matrix(pose)
    np.testing.assert_allclose(T, pose_to_matrix(pose[:3], pose[3:]))
    pos, rv = matrix_to_pose(T)
    np.testing.assert_allclose(np.concatenate([pos, rv]), pose, atol=1e-12)


def _ik_reference(kin, solved, q_current):
    """`Kinematics.ik` as it was, in batched numpy on `solved` = kin._solve_numpy(T, q_current[5])."""
    q_current = np.asarray(q_current, dtype=float).reshape(6)
    Q, valid, why = solved
    if not valid.any():
        raise UnreachableError(f"no IK solution: {why}")
    Q = Q[valid]
    k0 = np.round((q_current - Q) / (2 * np.pi))
    cand = Q[None] + 2 * np.pi * (k0[None] + np.array([-1.0, 0.0, 1.0])[:, None, None])
    inside = (cand >= kin.lower - 1e-9) & (cand <= kin.upper + 1e-9)
    cost = np.where(inside, np.abs(cand - q_current), np.inf)
    best = np.argmin(cost, axis=0)
    sol = np.take_along_axis(cand, best[None], axis=0)[0]
    err = np.take_along_axis(cost, best[None], axis=0)[0]
    ok = np.isfinite(err).all(axis=1)
    if not ok.any():
        raise UnreachableError(
            f"the {kin.variant.name} reaches this pose in {len(Q)} configuration(s), but none within its "
            f"joint limits; choose another TCP orientation or unwind the wrist first")
    sol, err = sol[ok], err[ok]
    return np.clip(sol[np.argmin((err**2).sum(axis=1))], kin.lower, kin.upper)


def _hard_cases(kin, n, seed):
    """(Q, poses): random configurations, a third of them at or near the wrist / elbow singularities, plus
    targets on the reach boundary (arm stretched, nudged in and out) and the shoulder boundary (wrist centre
    d4 from the base axis), some just outside it, and the two kinds of unreachable targets."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(kin.lower, kin.upper, size=(n, 6))
    k = n // 6
    Q[:k, 4] = rng.choice([0.0, np.pi, -np.pi, 1e-13, 1e-11, 1e-9, -1e-7, 1e-4], k)  # wrist: q5 ~ 0, pi
    Q[k:2 * k, 2] = rng.choice([0.0, 1e-12, -1e-9, 1e-6, np.pi, np.pi - 1e-9, -np.pi + 1e-6], k)  # elbow
    Q[2 * k:3 * k, [2, 4]] = 0.0
    poses = list(kin.fk_batch(Q))
    stretched = Q[3 * k:4 * k].copy()
    stretched[:, 2] = 0.0
    for T in kin.fk_batch(stretched):
        rel = rng.choice([0.0, 1e-12, -1e-12, 1e-10, 5e-10, -5e-10, 2e-9, -1e-3, 1e-3])
        T[:3, 3] *= 1 + rel  # along the base->TCP line: in or out of reach by about rel * 0.9 m
        poses.append(T)
    for T in kin.fk_batch(Q[4 * k:5 * k]):
        F = T @ np.linalg.inv(kin.tcp_offset)
        w = F[:2, 3] - kin.d[5] * F[:2, 2]  # wrist centre, horizontal
        target = kin.d[3] * (1 + rng.choice([0.0, 1e-12, -1e-12, 1e-9, -2e-9, -1e-3]))
        T[:2, 3] += (target / np.hypot(*w) - 1) * w
        poses.append(T)
    poses += [pose_to_matrix([1.5, 0.3, 0.4], [np.pi, 0, 0]), pose_to_matrix([0.0, 0.0, 0.5], [0, 0, 0])]
    return Q, poses


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_scalar_paths_match_batched_numpy(variant):
    """fk / fk_flange / jacobian / ik_all / ik (scalar math) agree with the batched numpy implementations."""
    R = rotvec_to_matrix([0.3, -1.1, 0.6])
    odd_tcp = pose_to_matrix([0.01, -0.02, 0.15], matrix_to_rotvec(R))
    for kin in (Kinematics.with_tcp_z(variant, TCP_OFFSET_Z), Kinematics(variant, odd_tcp)):
        Q, poses = _hard_cases(kin, 600, seed=7)
        # FK and the Jacobian: to rounding, everywhere.
        T_batch, F_batch, frames = kin.fk_batch(Q), kin.fk_flange_batch(Q), kin.frames_batch(Q)
        for q, T, Tf, F in zip(Q, T_batch, F_batch, frames):
            assert np.abs(kin.fk(q) - T).max() <= 1e-12, q
            assert np.abs(kin.fk_flange(q) - Tf).max() <= 1e-12, q
            z, o = F[:6, :3, 2], F[:6, :3, 3]
            J = np.vstack([np.cross(z, T[:3, 3] - o).T, z.T])
            assert np.abs(kin.jacobian(q) - J).max() <= 1e-12, q
        # IK: the same branches exist, each gives the same pose, and the joint angles agree to 1e-12 wherever
        # they are well conditioned. At a singularity (sin q3 or sin q5 ~ 0, wrist centre ~ d4 from the base
        # axis) the angles are ill-conditioned: a rounding-level change of the pose moves them by up to ~1e-6
        # in either implementation (only q4 + q6 is defined at q5 = 0, say), so there only the pose is compared.
        rng = np.random.default_rng(8)
        n_tight = 0
        for i, T in enumerate(poses):
            q_cur = Q[i % len(Q)] + rng.normal(0.0, 0.3, 6)
            Q_fast, valid = kin.ik_all(T, q6_hint=q_cur[5])
            solved = kin._solve_numpy(T, q_cur[5])
            Q_ref, valid_ref, _ = solved
            np.testing.assert_array_equal(valid, valid_ref, err_msg=str(i))
            assert np.isnan(Q_fast[~valid]).all()
            F = T @ kin._tcp_inv
            shoulder_ok = np.hypot(*(F[:2, 3] - kin.d[5] * F[:2, 2])) > kin.d[3] * 1.001

            def conditioned(sols):
                return shoulder_ok & (np.minimum(np.abs(np.sin(sols[..., 2])), np.abs(np.sin(sols[..., 4]))) > 0.01)

            if valid.any():
                a, b = Q_fast[valid], Q_ref[valid]
                assert np.all(a > -np.pi) and np.all(a <= np.pi)
                assert np.abs(kin.fk_batch(a) - kin.fk_batch(b)).max() <= 1e-12, i
                tight = conditioned(b)
                assert np.abs(wrap_angle(a - b))[tight].max(initial=0.0) <= 1e-12, i
                n_tight += tight.sum()
            try:
                expected, expected_error = _ik_reference(kin, solved, q_cur), None
            except UnreachableError as e:
                expected, expected_error = None, str(e)
            if expected is None:
                with pytest.raises(UnreachableError) as info:
                    kin.ik(T, q_cur)
                assert str(info.value) == expected_error
                continue
            got = kin.ik(T, q_cur)
            assert np.abs(kin.fk(got) - kin.fk(expected)).max() <= 1e-12, i
            assert np.abs(got - expected).max() <= 1e-5, i  # the same branch and the same turns
            if conditioned(expected):
                assert np.abs(got - expected).max() <= 1e-12, i
        assert n_tight > 4 * len(Q)  # most branches of most poses are compared angle by angle


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's, on the NaN / inf fallback path
def test_scalar_paths_fall_back_for_non_finite_input():
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    for bad in (np.nan, np.inf):
        q = np.array([0.1, -1.0, 1.2, bad, 0.5, 0.0])
        np.testing.assert_array_equal(kin.fk(q), kin.fk_batch(q)[0])
        T = kin.fk([0.1, -1.0, 1.2, 0.3, 0.5, 0.0])
        T[0, 3] = bad
        Q, valid = kin.ik_all(T)
        assert not valid.any() and np.isnan(Q).all()
        with pytest.raises(UnreachableError, match="no IK solution"):
            kin.ik(T, np.zeros(6))
        with pytest.raises(UnreachableError, match="none within its joint limits"):
            kin.ik(kin.fk(np.zeros(6) + 0.3), q)
