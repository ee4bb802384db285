"""Views on the way to drawer_put's later grasps (datagen/views_stages.py): the scene as the collector leaves it
(the drawer open; then the object in it), the arm setting out from the last release, the labels of that grasp
cycle, measured on that cycle of recorded episodes and kept apart from the first grasp's in the views' files."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.articulated import OPEN_TARGET
from datagen.views import generate, load, measure_offsets, scene_views, tasks
from datagen.views_stages import drop_point, label_key, parse_key, set_stage
from sim.build import build_episode
from sim.state import StateView
from sim.tasks.drawer import CABINET, SLIDE

SIZE = (32, 32)
HANDLE = f"{CABINET}/handle_site"
SEED = 212000
ZERO = {"grasp": np.zeros(3), "release": np.zeros(3)}


def test_label_keys_name_the_later_stages_and_refuse_unknown_ones():
    assert label_key("drawer_put") == label_key("drawer_put", "handle") == "drawer_put"
    assert label_key("drawer_put", "object") == "drawer_put/object"
    assert parse_key("drawer_put/close") == ("drawer_put", 2) and parse_key("pick_place") == ("pick_place", 0)
    with pytest.raises(ValueError, match="expected one of handle, object, close"):
        label_key("drawer_put", "lid")
    with pytest.raises(ValueError, match="pick_place grasps once"):
        parse_key("pick_place/object")


def test_the_object_stage_opens_the_drawer_and_labels_the_object_and_the_drawer_floor():
    off = {"grasp": np.array([0.0, 0.0, 0.007]), "release": np.array([0.0, 0.0, 0.12])}
    v = scene_views(SEED, 4, off, image_size=SIZE, task="drawer_put", stage="object")
    ep = build_episode("drawer_put", SEED, "heavy", "fast")
    shut_handle = StateView(ep.world).position(HANDLE)
    obj = StateView(ep.world).position(ep.instance.params["target"])
    set_stage(ep, 1)
    state = StateView(ep.world)
    assert state.joint_fraction(SLIDE) == pytest.approx(OPEN_TARGET)
    R = state.rotation(CABINET)
    np.testing.assert_allclose(v["points"][:, 0], np.broadcast_to(obj + R @ off["grasp"], (4, 3)), atol=1e-5)
    np.testing.assert_allclose(v["points"][:, 1], np.broadcast_to(drop_point(ep) + R @ off["release"], (4, 3)),
                               atol=1e-5)
    assert np.linalg.norm(state.position(HANDLE) - shut_handle) > 0.1  # the handle did come out
    # the first view is where the arm let go of the handle: above it, not at home
    np.testing.assert_allclose(v["proprio"][0, :3], state.position(HANDLE) + [0, 0, 0.10], atol=5e-3)
    from sim.tasks.pick_place import footprint_period

    # the object's own grasp axis (a block's footprint turns; a handle has none): here it is the object grasped
    period = footprint_period(ep.instance.obj(ep.instance.params["target"])) or 0.0
    assert v["footprint_period"][0] == pytest.approx(period) and v["stage"] == ["object"] * 4


def test_at_home_object_views_show_the_start_with_the_object_stages_labels():
    off = {"grasp": np.array([0.0, 0.0, 0.007]), "release": np.array([0.0, 0.0, 0.12])}
    later = scene_views(SEED, 2, off, image_size=SIZE, task="drawer_put", stage="object")
    home = scene_views(SEED, 2, off, image_size=SIZE, task="drawer_put", stage="object", at_home=True)
    first = scene_views(SEED, 2, off, image_size=SIZE, task="drawer_put")  # the start, the handle's labels
    np.testing.assert_allclose(home["points"], later["points"], atol=1e-6)  # where the object and the drop are
    assert home["at_home"].all() and not later["at_home"].any() and home["stage"] == ["object"] * 2
    np.testing.assert_allclose(home["proprio"][0], first["proprio"][0], atol=1e-6)  # the arm at home
    assert np.array_equal(home["scene"][0], first["scene"][0])  # and the drawer shut: the start's very image
    assert not np.array_equal(home["scene"][0], later["scene"][0])
    with pytest.raises(ValueError, match="at_home views label an object's grasp"):
        scene_views(SEED, 1, off, image_size=SIZE, task="drawer_put", stage="close", at_home=True)
    with pytest.raises(ValueError, match="at_home views label an object's grasp"):
        scene_views(SEED, 1, off, image_size=SIZE, task="drawer_put", at_home=True)  # the handle's grasp


def test_drawer_stows_views_label_the_object_and_the_open_drawers_floor_from_the_start():
    off = {"grasp": np.array([0.0, 0.0, 0.007]), "release": np.array([0.0, 0.0, 0.12])}
    home = scene_views(SEED, 2, off, image_size=SIZE, task="drawer_stow", at_home=True)
    plain = scene_views(SEED, 2, off, image_size=SIZE, task="drawer_stow")
    ep = build_episode("drawer_stow", SEED, "heavy", "fast")
    state = StateView(ep.world)
    assert state.joint_fraction(SLIDE) > 0.8  # the drawer open from the start: nothing to set
    R = state.rotation(CABINET)
    obj = state.position(ep.instance.params["target"])
    np.testing.assert_allclose(home["points"][:, 0], np.broadcast_to(obj + R @ off["grasp"], (2, 3)), atol=1e-5)
    np.testing.assert_allclose(home["points"][:, 1], np.broadcast_to(drop_point(ep) + R @ off["release"], (2, 3)),
                               atol=1e-5)
    # the same scene and the same first view as the first grasp's own views; only the flag tells the question
    assert home["at_home"].all() and not plain["at_home"].any() and home["stage"] == [""] * 2
    assert np.array_equal(home["scene"][0], plain["scene"][0])
    np.testing.assert_allclose(home["points"], plain["points"], atol=1e-6)


def test_the_close_stage_puts_the_object_in_the_open_drawer_and_labels_the_handle_to_push_shut():
    v = scene_views(SEED, 2, ZERO, image_size=SIZE, task="drawer_put", stage="close")
    ep = build_episode("drawer_put", SEED, "heavy", "fast")
    set_stage(ep, 2)
    state = StateView(ep.world)
    assert state.inside(ep.instance.params["target"], CABINET)
    np.testing.assert_allclose(v["points"][0, 0], state.position(HANDLE), atol=1e-5)
    lo, _ = state.joint_range(SLIDE)
    ep.world.data.qpos[ep.world.model.jnt_qposadr[ep.world.model.joint(SLIDE).id]] = lo
    ep.world.forward()
    np.testing.assert_allclose(v["points"][0, 1], StateView(ep.world).position(HANDLE), atol=1e-5)


def _recorded(root, seeds_cycles: dict, offsets: dict):
    """drawer_put episodes whose gripper closes `cycles` times; the commanded positions at each grasp and
    release are that stage's anchors plus `offsets[stage]` in the cabinet's frame."""
    from datagen.store import ShardWriter
    from datagen.views_stages import stage_anchors
    from datagen.workers import synthetic_episode

    T = 60
    with ShardWriter(root, "w0") as w:
        for seed, cycles in seeds_cycles.items():
            ep = synthetic_episode("drawer_put", seed, steps=T, size=16)
            ep.action[:, -1] = 0.0
            for k in range(cycles):
                g, r = 5 + 15 * k, 12 + 15 * k
                ep.action[g:r, -1] = 1.0
                stage = min(k, 2)
                built = build_episode("drawer_put", seed, "heavy", ep.meta.get("fidelity", "fast"))
                set_stage(built, stage)
                a = stage_anchors(built, stage)
                o = offsets[stage]
                ep.action[g, :3] = a.grasp + a.frame @ o["grasp"]
                ep.action[r, :3] = a.release + a.frame @ o["release"]
            ep.meta["success"] = True
            ep.meta["label"] = {"value": True}
            w.append(ep)
    return root


def test_offsets_are_measured_on_the_stages_own_cycle_of_episodes_that_made_one_per_stage(tmp_path):
    offsets = [{"grasp": np.array([0.0, 0.0, -0.004]), "release": np.array([0.0, -0.15, -0.004])},
               {"grasp": np.array([0.01, 0.0, 0.007]), "release": np.array([0.0, -0.01, 0.12])},
               {"grasp": np.array([0.0, 0.002, -0.003]), "release": np.array([0.0, 0.005, -0.003])}]
    wrong = [{k: v + 0.05 for k, v in o.items()} for o in offsets]
    data = _recorded(tmp_path / "a", {1: 3, 2: 3}, offsets)
    _recorded(tmp_path / "b", {3: 4}, wrong)  # a retry's fourth cycle: its stages cannot be told apart
    from datagen.store import Dataset

    for key, stage in (("drawer_put/object", 1), ("drawer_put/close", 2)):
        got = measure_offsets(data, key)
        assert got["episodes"] == 2
        for k in ("grasp", "release"):
            np.testing.assert_allclose(got[k], offsets[stage][k], atol=1e-5)
    assert len(Dataset(tmp_path / "b")) == 1
    with pytest.raises(ValueError, match="no successful drawer_put episode to measure the label offsets of "
                                         "drawer_put/object"):
        measure_offsets(tmp_path / "b", "drawer_put/object")


def test_stage_views_keep_their_own_offsets_in_the_files(tmp_path):
    generate(tmp_path, range(SEED, SEED + 1), 2, ZERO, progress=False, image_size=SIZE, task="drawer_put")
    generate(tmp_path, range(SEED, SEED + 1), 2, ZERO, progress=False, image_size=SIZE, task="drawer_put",
             stage="object")
    assert tasks(tmp_path) == ["drawer_put", "drawer_put/object"]
    a = load(tmp_path)
    moved = {"drawer_put": ZERO, "drawer_put/object": {"grasp": np.array([0.0, 0.0, 0.01]), "release": np.zeros(3)}}
    b = load(tmp_path, moved)
    later = a["stage"] == "object"
    assert later.sum() == 2
    np.testing.assert_allclose(b["points"][later, 0] - a["points"][later, 0], [[0, 0, 0.01]] * 2, atol=1e-6)
    np.testing.assert_allclose(b["points"][~later], a["points"][~later], atol=1e-7)
    with pytest.raises(ValueError, match="no label offsets for drawer_put/object"):
        load(tmp_path, {"drawer_put": ZERO})
