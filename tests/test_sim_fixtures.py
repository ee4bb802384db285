"""sim.fixtures and runtime.sim_cell: the scene's fixtures become the safety filter's keep-out boxes."""

from __future__ import annotations

import warnings

import mujoco
import numpy as np
import pytest

from runtime.sim_cell import cell_limits
from safety import SafetyFilter, default_limits, load_limits
from sim.build import build_episode
from sim.fixtures import fixture_boxes

warnings.simplefilter("ignore", UserWarning)


def _inside(box, p, tol=1e-9) -> bool:
    return all(box[i] - tol <= p[i] <= box[i + 3] + tol for i in range(3))


@pytest.fixture(scope="module")
def bins_episode():
    return build_episode("pick_place", 100019, "heavy", "fast")


def test_each_bin_wall_and_floor_is_a_box_and_the_cavity_stays_free(bins_episode):
    w = bins_episode.world
    m, d = w.model, w.data
    mujoco.mj_kinematics(m, d)
    boxes = fixture_boxes(m, d)
    walls = [g for g in range(m.ngeom) if m.geom(g).name.startswith("bin_")]
    assert len(boxes) == len(walls) and len(walls) % 5 == 0  # floor + 4 walls per bin
    for g in walls:  # every corner of every wall geom lies in some box
        R, c, h = d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g], m.geom_size[g]
        for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            assert any(_inside(b, c + R @ (s * h), 1e-6) for b in boxes)
    for site in range(m.nsite):  # the inside of each bin, where objects are dropped, is not kept out
        if m.site(site).name.endswith("/inside"):
            assert not any(_inside(b, d.site_xpos[site], 0.0) for b in boxes)
    tcp = w.tcp_pose()[:3, 3]
    assert not any(_inside(b, tcp) for b in boxes)


def test_a_sliding_drawer_is_not_a_fixture_but_its_cabinet_is():
    w = build_episode("drawer_put", 5, "heavy", "fast").world
    m, d = w.model, w.data
    mujoco.mj_kinematics(m, d)
    boxes = fixture_boxes(m, d)
    carcass = [g for g in range(m.ngeom) if m.body(m.geom_bodyid[g]).name == "cabinet"
               and (m.geom_contype[g] or m.geom_conaffinity[g])]
    drawer = [g for g in range(m.ngeom) if m.body(m.geom_bodyid[g]).name == "cabinet/drawer"]
    assert carcass and drawer and len(boxes) >= len(carcass)
    for b in boxes:  # every box is a piece of a carcass panel: its centre lies in one
        centre = np.array([(b[i] + b[i + 3]) / 2 for i in range(3)])
        local = [d.geom_xmat[g].reshape(3, 3).T @ (centre - d.geom_xpos[g]) for g in carcass]
        assert any(np.all(np.abs(x) <= m.geom_size[g] + 1e-9) for x, g in zip(local, carcass))
    for g in drawer:  # the drawer slides: it is no fixture, and the boxes around the turned panels leave it free
        assert not any(_inside(b, d.geom_xpos[g], 0.0) for b in boxes)


def test_a_turned_panel_is_cut_into_boxes_that_hug_it():
    from sim.fixtures import OVERHANG, _pieces

    yaw = np.radians(10)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    half = np.array([0.005, 0.12, 0.055])  # a cabinet side: thin along x, long along y
    pieces = list(_pieces(R, half))
    assert len(pieces) > 1 and np.isclose(sum(2 * ph[1] for _, ph in pieces), 2 * half[1])
    for pc, ph in pieces:  # the world box's x half-width exceeds the panel's own by at most OVERHANG
        assert (np.abs(R) @ ph)[0] <= half[0] + OVERHANG + 1e-12
    assert len(list(_pieces(np.eye(3), half))) == 1  # an axis-aligned bin wall stays one box


def _off_box(R, half, p) -> float:
    """How far world point p (in the box's centred frame) lies outside the turned box."""
    return float(np.linalg.norm(np.maximum(np.abs(R.T @ p) - half, 0.0)))


@pytest.mark.parametrize("yaw_deg", [5.0, 10.0, 11.5])
def test_a_flat_panel_turned_in_yaw_is_cut_so_no_box_stands_off_its_edges(yaw_deg):
    """A cabinet's top panel (flat, 26 x 27 cm) turned in yaw: its one world box reached 4.4 cm in front of the
    drawer's face at 10 degrees, where the fingers take the handle; every piece's box now hugs it."""
    from sim.fixtures import OVERHANG, _pieces

    yaw = np.radians(yaw_deg)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    half = np.array([0.13, 0.135, 0.005])
    corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3)
    one_box = max(_off_box(R, half, s * (np.abs(R) @ half)) for s in corners)
    assert one_box > 0.02  # what a single world box around it stands off
    pieces = list(_pieces(R, half))
    assert np.isclose(sum(np.prod(2 * ph) for _, ph in pieces), np.prod(2 * half))  # the panel, all of it
    worst = max(_off_box(R, half, R @ pc + s * (np.abs(R) @ ph)) for pc, ph in pieces for s in corners)
    assert worst <= 2 * OVERHANG


def test_cell_limits_keep_the_users_boxes_and_reach_the_filter(bins_episode):
    user = (-0.6, 0.7, 0.3, -0.5, 0.8, 0.4)
    lim = cell_limits(load_limits(None, "ur5e", {"workspace.keepout": [list(user)]}), bins_episode.world)
    assert lim.workspace.keepout[0] == user and len(lim.workspace.keepout) == 1 + 15
    assert default_limits("ur5e").workspace.keepout == ()  # the defaults are not changed
    filt = SafetyFilter(lim, collision=False)
    bin_wall = lim.workspace.keepout[2]  # a wall: a target with the TCP in it is not admissible
    centre = [(bin_wall[i] + bin_wall[i + 3]) / 2 for i in range(3)]
    assert not filt.workspace.target_ok([tuple(centre)])
