"""Test set-up on the sim twins and the MuJoCo 2F-85 shared by the controller, gripper and safety tests."""

from __future__ import annotations


def hand_a_block_to_the_fingers(rig):
    """One of the pick_place world's objects, made weightless (gravcomp) and teleported between the open
    fingers, as a hand would hold it there."""
    import mujoco

    world = rig.world
    m = world.model
    jnt = next(j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
    adr, dof, body = m.jnt_qposadr[jnt], m.jnt_dofadr[jnt], m.jnt_bodyid[jnt]
    with rig.lock:
        m.body_gravcomp[body] = 1.0
        world.data.qpos[adr:adr + 3] = world.tcp_pose()[:3, 3]
        world.data.qpos[adr + 3:adr + 7] = [1, 0, 0, 0]
        world.data.qvel[dof:dof + 6] = 0
        world.forward()


def gripper_at(ctrl: float, home):
    """sim.robot's UR5e with the 2F-85 closed on nothing by `ctrl` (0 open .. 255) from joints `home`:
    (model, data, closure as the sim gripper measures it)."""
    import mujoco
    import numpy as np

    from sim.robot import robot_spec
    from sim.world import GRIPPER_MAX_DRIVER

    model = robot_spec("ur5e").compile()
    data = mujoco.MjData(model)
    drivers = [model.jnt_qposadr[j] for j in range(model.njnt) if "driver" in model.joint(j).name]
    data.qpos[:6] = home
    data.ctrl[-1] = ctrl
    for _ in range(1500):
        mujoco.mj_step(model, data)
    return model, data, float(np.clip(data.qpos[drivers].mean() / GRIPPER_MAX_DRIVER, 0.0, 1.0))


def pad_geoms(model) -> list[int]:
    """The 2F-85's pad collision geoms."""
    from sim.robot import GRIPPER_PREFIX

    return [g for g in range(model.ngeom) if model.geom_contype[g]
            and model.body(model.geom_bodyid[g]).name.startswith(GRIPPER_PREFIX)
            and "pad" in model.body(model.geom_bodyid[g]).name]


def pad_corners_in_tcp(model, data):
    """Per pad geom, its box's eight corners in the TCP frame (x across the gap, z along the approach)."""
    import numpy as np

    from sim.robot import TCP_SITE

    s = data.site(TCP_SITE)
    R, p = s.xmat.reshape(3, 3), s.xpos
    unit = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    return [(unit * model.geom_size[g] @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g] - p) @ R
            for g in pad_geoms(model)]
