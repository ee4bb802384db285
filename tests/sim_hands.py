"""Test set-up on the sim twins shared by the controller and gripper tests."""

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
