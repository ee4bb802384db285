"""sim.fidelity: the fast robot looks simpler but simulates identically; sim.bench reports its figures."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before the first mujoco import: headless rendering

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from sim.bench import bench_scene, run_sim_bench  # noqa: E402
from sim.fidelity import FIDELITY_LEVELS, apply_fidelity, model_fidelity, render_settings  # noqa: E402
from sim.render import CameraRenderer  # noqa: E402
from sim.scene import SCENE_CAMERA, base_scene  # noqa: E402
from sim.world import World  # noqa: E402


@pytest.fixture(scope="module")
def models() -> dict[str, mujoco.MjModel]:
    return {level: bench_scene(level).compile() for level in FIDELITY_LEVELS}


def _names(model, obj, n):
    return [mujoco.mj_id2name(model, obj, i) for i in range(n)]


def _collision_geoms(model):
    rows = []
    for g in range(model.ngeom):
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        mesh = int(model.geom_dataid[g])
        mesh_verts = int(model.mesh_vertnum[mesh]) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH else -1
        rows.append((
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g])),
            mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g),
            int(model.geom_type[g]), tuple(model.geom_size[g]), tuple(model.geom_pos[g]), tuple(model.geom_quat[g]),
            int(model.geom_contype[g]), int(model.geom_conaffinity[g]), int(model.geom_condim[g]),
            int(model.geom_priority[g]), tuple(model.geom_friction[g]), tuple(model.geom_solref[g]),
            tuple(model.geom_solimp[g]), float(model.geom_margin[g]), float(model.geom_gap[g]), mesh_verts,
        ))
    return rows


def _drawn_mesh_vertices(model) -> int:
    meshes = {int(model.geom_dataid[g]) for g in range(model.ngeom)
              if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] <= 2}
    return int(sum(model.mesh_vertnum[m] for m in meshes))


def test_unknown_level_lists_the_allowed_ones():
    spec = base_scene()
    with pytest.raises(ValueError, match="full.*fast"):
        apply_fidelity(spec, "ultra")
    with pytest.raises(ValueError, match="full.*fast"):
        render_settings("ultra")


def test_levels_are_recorded_and_idempotent():
    spec = base_scene()
    apply_fidelity(spec, "fast")
    apply_fidelity(spec, "fast")  # a second call is a no-op
    with pytest.raises(ValueError):
        apply_fidelity(spec, "full")  # the meshes are gone: full cannot be restored
    assert model_fidelity(spec.compile()) == "fast"
    assert model_fidelity(base_scene().compile()) == "full"
    assert render_settings("full").shadows and not render_settings("fast").shadows


def test_fast_keeps_the_physics(models):
    full, fast = models["full"], models["fast"]
    for obj, n in ((mujoco.mjtObj.mjOBJ_BODY, "nbody"), (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
                   (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"), (mujoco.mjtObj.mjOBJ_EQUALITY, "neq"),
                   (mujoco.mjtObj.mjOBJ_TENDON, "ntendon"), (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
                   (mujoco.mjtObj.mjOBJ_CAMERA, "ncam")):
        assert getattr(full, n) == getattr(fast, n)
        assert _names(full, obj, getattr(full, n)) == _names(fast, obj, getattr(fast, n))
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat",
                  "jnt_range", "dof_damping", "dof_armature", "actuator_gainprm", "actuator_biasprm"):
        np.testing.assert_array_equal(getattr(full, field), getattr(fast, field), err_msg=field)
    assert _collision_geoms(full) == _collision_geoms(fast)
    assert fast.nexclude == full.nexclude


def test_fast_simulates_identically(models):
    worlds = [World(models[level]) for level in FIDELITY_LEVELS]
    for world in worlds:
        world.set_arm_target(np.asarray(world.variant.home) + 0.25)
        world.set_gripper(1.0)
        world.step(300)
    np.testing.assert_array_equal(worlds[0].data.qpos, worlds[1].data.qpos)
    np.testing.assert_array_equal(worlds[0].data.qvel, worlds[1].data.qvel)


def test_fast_draws_far_fewer_vertices(models):
    full, fast = models["full"], models["fast"]
    assert _drawn_mesh_vertices(full) > 300_000
    assert _drawn_mesh_vertices(fast) < _drawn_mesh_vertices(full) / 50
    assert fast.nmeshvert < full.nmeshvert / 5  # the UR5e meshes are dropped from the model, not just hidden
    assert fast.nmesh < full.nmesh


@pytest.mark.parametrize("level", FIDELITY_LEVELS)
def test_both_levels_render_the_robot(models, level):
    world = World(models[level])
    with CameraRenderer(world, 96, 72) as renderer:
        assert renderer.shadows == render_settings(level).shadows
        image = renderer.rgb(SCENE_CAMERA)
        renderer._option.geomgroup[2] = 0  # hide the robot's visual geoms
        without_robot = renderer.rgb(SCENE_CAMERA)
    assert image.shape == (72, 96, 3) and image.std() > 10
    robot_pixels = np.any(np.abs(image.astype(int) - without_robot.astype(int)) > 20, axis=-1)
    assert robot_pixels.mean() > 0.02, f"the robot covers only {robot_pixels.mean():.1%} of the image"


def test_quick_bench_reports_positive_figures():
    result = run_sim_bench(quick=True)
    assert result["machine"]["cpu_count"] >= 1 and "mujoco_gl" in result["machine"]
    assert result["physics"]["steps_per_s"] > 0
    for level in FIDELITY_LEVELS:
        for key in ("spec_s", "compile_cold_s", "compile_warm_s", "total_cold_s", "total_warm_s"):
            assert result["build"][level][key] > 0
    assert set(result["renders_per_s"]["full"]) == {"128x128", "320x240"}
    assert set(result["renders_per_s"]["fast"]) == {"128x128", "320x240", "640x480"}
    for level in FIDELITY_LEVELS:
        assert all(v > 0 for v in result["renders_per_s"][level].values())
    assert all(v > 0 for v in result["fast_over_full"].values())
    json.dumps(result)  # JSON-able as it is
