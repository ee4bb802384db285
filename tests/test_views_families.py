"""Views of the other task families (datagen/view_anchors.py): labels hang on the blocks and on the drawer handle,
the handle's in the cabinet's frame."""

import numpy as np
import pytest

from datagen.views import generate, load, measure_offsets, scene_views, tasks
from sim.build import build_episode
from sim.state import StateView
from sim.tasks.drawer import CABINET, TRAVEL, set_drawer

SIZE = (32, 32)
# the drawer_open offsets: grasp at the handle, release with the handle pulled out by the whole travel
PULL = {"grasp": np.array([0.0, 0.0, -0.003]), "release": np.array([0.0, -TRAVEL, -0.003])}
HANDLE = f"{CABINET}/handle_site"


def _cabinet_turned(task: str) -> int:
    """A seed whose cabinet is turned clearly away from the world's axes, so a world-frame offset would miss."""
    for seed in range(400, 460):
        ep = build_episode(task, seed, "heavy", "fast")
        if abs(ep.instance.params["cabinet"]["yaw"]) > 0.08:
            return seed
    raise AssertionError("no seed with a turned cabinet")


def test_a_drawer_views_release_point_is_where_the_handle_is_with_the_drawer_pulled_out():
    seed = _cabinet_turned("drawer_open")
    v = scene_views(seed, 3, PULL, image_size=SIZE, task="drawer_open")
    ep = build_episode("drawer_open", seed, "heavy", "fast")
    state = StateView(ep.world)
    handle = state.position(HANDLE)
    np.testing.assert_allclose(v["points"][:, 0], np.broadcast_to(handle + [0, 0, -0.003], (3, 3)), atol=1e-5)
    set_drawer(ep.world, TRAVEL)  # the drawer really pulled out: where its handle went
    pulled = StateView(ep.world).position(HANDLE) + [0, 0, -0.003]
    np.testing.assert_allclose(v["points"][:, 1], np.broadcast_to(pulled, (3, 3)), atol=1e-5)
    assert v["task"] == ["drawer_open"] * 3 and v["footprint_period"].max() == 0.0  # a handle names no axis
    assert v["instruction"][0] == ep.instruction


def test_a_closing_views_release_point_is_the_handle_with_the_drawer_shut():
    seed = _cabinet_turned("drawer_close")
    shut = {"grasp": np.zeros(3), "release": np.zeros(3)}
    v = scene_views(seed, 2, shut, image_size=SIZE, task="drawer_close")
    ep = build_episode("drawer_close", seed, "heavy", "fast")
    assert ep.instance.params["initial"] > 0.5 * TRAVEL
    set_drawer(ep.world, 0.0)
    np.testing.assert_allclose(v["points"][0, 1], StateView(ep.world).position(HANDLE), atol=1e-5)


def test_stack_views_hang_on_the_top_block_and_the_block_under_it():
    off = {"grasp": np.array([0.0, 0.0, 0.007]), "release": np.array([0.0, 0.0, 0.06])}
    v = scene_views(401, 2, off, image_size=SIZE, task="stack")
    ep = build_episode("stack", 401, "heavy", "fast")
    state = StateView(ep.world)
    top, bottom = (state.position(ep.instance.params[k]) for k in ("top", "bottom"))
    np.testing.assert_allclose(v["points"][0], [top + off["grasp"], bottom + off["release"]], atol=1e-5)
    assert v["footprint_period"][0] > 0  # a block has a footprint to turn to


def test_relabelling_moves_a_drawers_labels_along_the_cabinets_axes(tmp_path):
    seed = _cabinet_turned("drawer_open")
    generate(tmp_path, range(seed, seed + 1), 2, PULL, progress=False, image_size=SIZE, task="drawer_open")
    generate(tmp_path, range(300, 301), 2, PULL, progress=False, image_size=SIZE, task="pick_place")
    assert tasks(tmp_path) == ["drawer_open", "pick_place"]
    longer = {"grasp": PULL["grasp"], "release": PULL["release"] + [0.0, -0.02, 0.0]}  # pulled 2 cm further
    a = load(tmp_path)
    b = load(tmp_path, {"drawer_open": longer, "pick_place": PULL})
    drawer = a["task"] == "drawer_open"
    R = a["frame"][drawer][0]
    np.testing.assert_allclose(b["points"][drawer, 1] - a["points"][drawer, 1],
                               np.broadcast_to(R @ [0.0, -0.02, 0.0], (2, 3)), atol=1e-6)
    assert abs((R @ [0.0, -0.02, 0.0])[0]) > 1e-3  # turned: not the world's -y
    np.testing.assert_allclose(b["points"][~drawer], a["points"][~drawer], atol=1e-7)
    with pytest.raises(ValueError, match="no label offsets for drawer_open"):
        load(tmp_path, {"pick_place": PULL})


def test_offsets_are_measured_per_family_and_an_unknown_one_is_named(tmp_path):
    from policy.testing import synthetic_dataset

    data = synthetic_dataset(tmp_path / "data", episodes=2, smooth=True)
    with pytest.raises(ValueError, match="no successful stack episode"):
        measure_offsets(data, "stack")
    with pytest.raises(ValueError, match="not 'pour'"):
        measure_offsets(data, "pour")
    with pytest.raises(ValueError, match="carrying views are of an object carried to its release"):
        scene_views(300, 1, PULL, image_size=SIZE, carry=1, task="drawer_open")


def test_sudd_views_names_a_family_it_cannot_label_and_carrying_views_of_a_handle(tmp_path, capsys):
    from runtime.cli import main

    base = ["views", "--out", str(tmp_path / "v"), "--scenes", "1", "--offsets-from", str(tmp_path)]
    assert main(base + ["--task", "pour"]) == 2
    assert "--task pour: views label the families pick_place, stack" in capsys.readouterr().err
    assert main(base + ["--task", "drawer_open", "--carry-views", "2"]) == 2
    assert "whose grasp is a handle" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()  # nothing rendered


def test_stack_carrying_views_hold_the_top_block_on_its_way_to_the_other():
    from datagen.recorder import TCP_OFFSET_Z
    from datagen.view_anchors import anchors
    from datagen.views_carry import grasp_in_hand, place_carried
    from sim.kinematics import Kinematics

    off = {"grasp": np.array([0.0, 0.0, 0.007]), "release": np.array([0.0, 0.0, 0.063])}
    v = scene_views(401, 1, off, image_size=SIZE, carry=3, task="stack")
    assert len(v["proprio"]) == 4  # home, then three carrying views
    assert np.all((v["proprio"][1:, 9] > 0.2) & (v["proprio"][1:, 9] < 0.9))  # closed on a block
    np.testing.assert_array_equal(v["points"][1:], np.broadcast_to(v["points"][0], (3, 2, 3)))
    ep = build_episode("stack", 401, "heavy", "fast")
    a = anchors(ep)
    assert a.carried == ep.instance.params["top"]
    kin = Kinematics.with_tcp_z(ep.world.variant, TCP_OFFSET_Z)
    in_tcp = grasp_in_hand(ep.world, kin, a.carried, v["points"][0, 0], a.yaw, ep.world.arm_q())
    T = ep.world.tcp_pose().copy()
    T[:3, 3] = v["points"][0, 1] + [0.0, 0.0, 0.05]  # above the bottom block
    place_carried(ep.world, kin, kin.ik(T, ep.world.arm_q()), a.carried, in_tcp)
    assert StateView(ep.world).holding(a.carried)
