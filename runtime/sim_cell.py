"""The sim twin's cell: the safety limits with the scene's fixtures (its bins) added as keep-out boxes.

A real cell declares its fixed furniture in the limits file (`sudd run --limits FILE`, `workspace.keepout`);
the sim twin knows where DR put this episode's, so `sudd eval` and `sudd run --sim` declare them the same
way (sim.fixtures says what counts and why).
"""

from __future__ import annotations

from dataclasses import replace

import mujoco


def cell_limits(limits, world):
    """`limits` with `world`'s fixtures appended to workspace.keepout (validated)."""
    from sim.fixtures import fixture_boxes

    mujoco.mj_kinematics(world.model, world.data)
    ws = limits.workspace
    out = replace(limits, workspace=replace(ws, keepout=tuple(ws.keepout) + fixture_boxes(world.model, world.data)))
    out.validate()
    return out


def sim_cell_ceiling(task: str, seed: int, dr: str, holdout, limits_file: str = "") -> float:
    """The highest fixture (runtime.free_pace.ceiling_of) of the cell the sim robot node of this episode declares:
    `limits_file` (or the variant's defaults) with the episode's fixtures, as runtime/nodes/robot_node.py builds it."""
    from runtime.free_pace import ceiling_of
    from safety import load_limits
    from sim.build import build_episode

    world = build_episode(task, seed, dr, "fast", holdout=holdout).world
    return ceiling_of(cell_limits(load_limits(limits_file or None, variant=world.variant.name), world))


__all__ = ["cell_limits", "sim_cell_ceiling"]
