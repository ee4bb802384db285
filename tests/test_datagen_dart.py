"""DART noise injection (datagen/dart.py): the executed path leaves the plan, the recorded actions do not."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from datagen.dart import envelope, grasp_envelope, joint_offsets, smooth_offsets, step_labels
from datagen.episode import DatagenConfig, run_episode
from datagen.trajectory import Motion, Segment
from sim.kinematics import Kinematics
from sim.robot import TCP_OFFSET_Z

DT = 0.002
HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])


def _motion() -> Motion:
    q1 = HOME + np.array([0.4, 0.2, -0.2, 0.0, 0.0, 0.0])
    move = Segment(np.linspace(0.0, 2.0, 11), np.linspace(HOME, q1, 11), 0.0, "move to pre-grasp")
    approach = Segment(np.linspace(0.0, 1.0, 6), np.linspace(q1, q1 + 0.05, 6), 0.0, "approach")
    return Motion([move, approach, Segment.hold(q1 + 0.05, 0.5, 1.0, "grasp")])


def _pick_motion() -> Motion:
    m = _motion()
    q = m.segments[-1].targets(DT)[-1]
    lift = Segment(np.linspace(0.0, 1.0, 6), np.linspace(q, q - 0.05, 6), 1.0, "lift")
    return Motion([*m.segments, lift])


def test_envelope_is_off_at_the_ends_and_while_the_gripper_acts_and_ramps_in_between():
    labels = step_labels(_motion(), DT)
    assert len(labels) == round(3.5 / DT)
    e = envelope(labels, DT, fade_s=0.5)
    assert e[0] == 0.0 and e[-1] == 0.0
    grasp = np.array([lab == "grasp" for lab in labels])
    assert np.all(e[grasp] == 0.0)  # the gripper closes exactly where the plan says
    assert np.all(np.abs(np.diff(e)) <= DT / 0.5 + 1e-12)  # no jumps: ramps of fade_s
    assert e.max() == 1.0 and np.all((0.0 <= e) & (e <= 1.0))


def test_grasp_envelope_is_whole_while_the_gripper_grasps_and_ramps_around_it():
    labels = step_labels(_pick_motion(), DT)
    g = grasp_envelope(labels, DT, fade_s=0.5)
    grasp = np.array([lab == "grasp" for lab in labels])
    assert np.all(g[grasp] == 1.0) and g[-1] == 0.0 and g[0] == 0.0
    ramp = np.flatnonzero(grasp)[0] - round(0.5 / DT)  # the approach's last fade_s rises to it
    assert g[ramp - 1] == 0.0 and 0.0 < g[ramp + 10] < 1.0
    assert np.all(np.abs(np.diff(g)) <= DT / 0.5 + 1e-12)


def test_grasp_offset_is_horizontal_constant_through_the_grasp_and_leaves_the_path_noise_alone():
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    motion = _pick_motion()
    plain = joint_offsets(motion, kin, DT, np.random.default_rng(3), sigma=0.02)
    dq = joint_offsets(motion, kin, DT, np.random.default_rng(3), sigma=0.02, grasp_sigma=0.01)
    labels = step_labels(motion, DT)
    g = grasp_envelope(labels, DT, 0.5)
    assert np.array_equal(dq[g == 0.0], plain[g == 0.0])  # the path's draws are those without it
    planned = np.concatenate([s.targets(DT) for s in motion.segments])
    grasp = np.flatnonzero(np.array([lab == "grasp" for lab in labels]))
    moved = np.array([kin.fk(planned[k] + dq[k])[:3, 3] - kin.fk(planned[k])[:3, 3] for k in grasp[::25]])
    assert np.linalg.norm(moved[0, :2]) > 0.002  # an offset of ~1 cm std: this draw is not near zero
    assert np.abs(moved[:, 2]).max() < 5e-4  # never vertical: the fingers stay off the table
    assert np.abs(moved - moved[0]).max() < 5e-4  # held while the fingers close


def test_offsets_have_the_asked_spread_and_move_smoothly():
    rng = np.random.default_rng(0)
    d = smooth_offsets(round(200.0 / DT), DT, sigma=0.015, tau_s=1.0, rng=rng)
    assert d.shape == (round(200.0 / DT), 3)
    assert 0.010 < float(d.std(axis=0).mean()) < 0.018  # the box filter takes a little off the OU's std
    assert float(np.abs(np.diff(d, axis=0)).max()) < 0.2 * DT  # < 0.2 m/s: nothing for the servo to chase


def test_joint_offsets_translate_the_tcp_by_the_enveloped_offset_and_keep_its_rotation():
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    motion = _motion()
    dq = joint_offsets(motion, kin, DT, np.random.default_rng(3), sigma=0.02)
    rng = np.random.default_rng(3)
    labels = step_labels(motion, DT)
    want = smooth_offsets(len(labels), DT, 0.02, 1.0, rng) * envelope(labels, DT, 0.5)[:, None]
    planned = np.concatenate([s.targets(DT) for s in motion.segments])
    assert np.abs(want).max() > 0.01  # the test would pass with no offset otherwise
    for k in range(0, len(planned), 97):
        T0, T1 = kin.fk(planned[k]), kin.fk(planned[k] + dq[k])
        moved = T1[:3, 3] - T0[:3, 3]  # first order in the offset: within 10 % of it (~1 mm at 4 cm)
        assert np.linalg.norm(moved - want[k]) <= 0.1 * np.linalg.norm(want[k]) + 1e-5, (k, moved, want[k])
        assert np.degrees(np.arccos(np.clip((np.trace(T0[:3, :3].T @ T1[:3, :3]) - 1) / 2, -1, 1))) < 0.5


@pytest.fixture(scope="module")
def clean_and_noisy():
    cfg = DatagenConfig(dr="light", max_retries=2)
    return run_episode("pick_place", 0, cfg), run_episode("pick_place", 0, replace(cfg, path_noise_cm=1.5))


def test_noisy_episode_keeps_the_plans_actions_and_leaves_its_path(clean_and_noisy):
    clean, noisy = clean_and_noisy
    assert clean.meta["success"] and noisy.meta["success"]
    assert noisy.meta["path_noise_cm"] == 1.5 and "path_noise_cm" not in clean.meta
    pick = int((clean.subtask == 0).sum())
    assert int((noisy.subtask == 0).sum()) == pick
    # the pick's plan is the same (its own random stream): the actions agree to the bit ...
    assert np.array_equal(clean.action[:pick - 1], noisy.action[:pick - 1])
    # ... while the arm went elsewhere on the way, and back onto the plan before the fingers closed
    dev = np.linalg.norm(clean.proprio[:pick, :3] - noisy.proprio[:pick, :3], axis=1)
    assert dev.max() > 0.01
    close = int(np.argmax(clean.action[:, 9] > 0.5))  # the step whose action closes the gripper
    assert dev[close] < 0.002


def test_grasp_noise_closes_the_fingers_off_the_plan_while_the_actions_keep_it():
    cfg = DatagenConfig(dr="light", max_retries=2)
    clean = run_episode("pick_place", 0, cfg)
    noisy = run_episode("pick_place", 0, replace(cfg, grasp_noise_cm=1.0))
    assert noisy.meta["grasp_noise_cm"] == 1.0 and "grasp_noise_cm" not in clean.meta
    close = int(np.argmax(clean.action[:, 9] > 0.5))
    assert np.array_equal(clean.action[:close + 1], noisy.action[:close + 1])
    dev = noisy.proprio[close, :3] - clean.proprio[close, :3]
    assert np.linalg.norm(dev[:2]) > 0.002 and abs(dev[2]) < 0.002
