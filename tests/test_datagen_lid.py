"""Hinged lids: open (grasp, lift, loosened carry to the stop) and close (fingertip push) across the task area."""

import numpy as np
import pytest

from datagen.primitives import Primitives
from datagen.trajectory import execute
from sim.objects import Placement, add_lid_box
from sim.scene import base_scene
from sim.state import StateView
from sim.world import World

# Corners and centre of x in [-0.25, 0.25], y in [0.4, 0.6], with yaw jitter of up to 0.3 rad.
PLACEMENTS = [(0.0, 0.5, 0.0), (0.22, 0.42, 0.3), (-0.22, 0.58, -0.3), (0.2, 0.58, 0.25), (-0.2, 0.42, -0.2)]


def _open_close(x, y, yaw):
    spec = base_scene()
    add_lid_box(spec, "box", Placement(x, y, yaw), (0.4, 0.6, 0.4, 1))
    world = World(spec.compile())
    world.step(100)
    state = StateView(world)
    prims = Primitives(world, np.random.default_rng(0))
    motion = prims.open("box/hinge")
    assert "loosen grasp" in motion.labels
    execute(world, motion)
    world.step(150)  # the data generator's settle time before a success check
    opened = state.joint_fraction("box/hinge")
    execute(world, prims.close("box/hinge"))
    world.step(150)
    return opened, state.joint_fraction("box/hinge")


@pytest.fixture(scope="module")
def results():
    return [_open_close(*p) for p in PLACEMENTS]


def test_lid_opens_across_the_task_area(results):
    opened = [o for o, _ in results]
    # Measured: 24/24 random placements open to ~0.94-0.96 after settling; allow one miss.
    assert sum(o >= 0.8 for o in opened) >= len(PLACEMENTS) - 1, opened
    assert max(opened) <= 1.02, opened  # driven to the stop, not through it


def test_lid_closes_across_the_task_area(results):
    closed = [c for _, c in results]
    assert sum(c <= 0.2 for c in closed) >= len(PLACEMENTS) - 1, closed


def test_close_of_a_closed_lid_keeps_it_closed():
    spec = base_scene()
    add_lid_box(spec, "box", Placement(0.1, 0.5), (0.4, 0.6, 0.4, 1))
    world = World(spec.compile())
    world.step(100)
    execute(world, Primitives(world, np.random.default_rng(1)).close("box/hinge"))
    assert StateView(world).joint_fraction("box/hinge") <= 0.2
