"""The assembled world: robot variants, cameras, parametric objects and their joints."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from sim.camera_model import D435_COLOR, Intrinsics
from sim.objects import Placement, add_bin, add_block, add_drawer_cabinet, add_lid_box
from sim.robot import ARM_JOINTS, WRIST_CAMERA, get_variant
from sim.scene import SCENE_CAMERA, base_scene
from sim.state import StateView
from sim.world import World


@pytest.mark.parametrize("variant", ["ur5e", "ur5"])
def test_variant_scene_builds_and_holds_home(variant):
    world = World(base_scene(variant).compile(), variant)
    home = np.array(get_variant(variant).home)
    world.step(500)
    assert np.allclose(world.arm_q(), home, atol=1e-3), "gravity-compensated servos hold the home pose"
    assert [world.model.joint(i).name for i in range(6)] == list(ARM_JOINTS)
    assert world.model.opt.timestep == pytest.approx(0.002)
    assert world.model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC


def test_unknown_variant_lists_the_known_ones():
    with pytest.raises(ValueError, match=r"expected one of \['ur5', 'ur5e'\]"):
        get_variant("ur10")


def test_scene_camera_has_d435_vertical_fov_and_wrist_camera_exists():
    model = base_scene().compile()
    assert model.cam_fovy[model.camera(SCENE_CAMERA).id] == pytest.approx(D435_COLOR.fovy_deg, abs=1e-6)
    assert model.camera(WRIST_CAMERA).id >= 0


def test_intrinsics_from_fovy_round_trip_and_scaling():
    k = Intrinsics.from_fovy(640, 480, 42.0)
    assert k.fovy_deg == pytest.approx(42.0)
    half = k.scaled(320, 240)
    assert half.fx == pytest.approx(k.fx / 2) and half.fovy_deg == pytest.approx(42.0)


def test_parametric_objects_move_on_their_joints():
    spec = base_scene()
    add_block(spec, "cube", (0.02, 0.02, 0.02), (1, 0, 0, 1), Placement(0.0, 0.45))
    add_bin(spec, "bin", (0.06, 0.07, 0.03), (0.3, 0.3, 0.3, 1), Placement(0.25, 0.6))
    add_drawer_cabinet(spec, "cab", Placement(-0.25, 0.62), (0.6, 0.5, 0.4, 1))
    add_lid_box(spec, "box", Placement(0.0, 0.68), (0.4, 0.6, 0.4, 1))
    world = World(spec.compile())
    state = StateView(world)
    world.step(200)
    assert state.on_top("cube", "table")
    # A push on the drawer slides it out; a torque on the lid hinge opens the lid.
    world.data.qfrc_applied[world.model.jnt_dofadr[world.model.joint("cab/slide").id]] = 20.0
    world.data.qfrc_applied[world.model.jnt_dofadr[world.model.joint("box/hinge").id]] = 0.5
    world.step(500)
    assert state.joint_fraction("cab/slide") > 0.5
    assert state.joint_value("box/hinge") > 0.5
    assert state.position("bin")[2] == pytest.approx(0.0), "bins are fixed furniture"
