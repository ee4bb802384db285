"""runtime/free_pace.py: a family slowed for its contacts plays at speed 1 while the hand is high above the cell."""

import json
from pathlib import Path

import pytest

from runtime.free_pace import BAND_M, CLEAR_M, FreePace, ceiling_of
from safety import default_limits, load_limits

EXAMPLE = Path(__file__).resolve().parents[1] / "safety" / "limits_example.toml"


def test_speed_one_above_the_line_and_the_familys_pace_below_it_with_a_band():
    free = FreePace(0.15)
    line = 0.15 + CLEAR_M
    assert free.speed(0.5, line + 0.01) == 1.0 and free.free
    assert free.speed(0.5, line - BAND_M / 2) == 1.0  # coming down: still free inside the band
    assert free.speed(0.5, line - BAND_M - 0.001) == 0.5 and not free.free
    assert free.speed(0.5, line - BAND_M / 2) == 0.5  # going up: free only above the line itself
    assert free.speed(0.5, line + 0.001) == 1.0
    assert free.ticks == 3


def test_a_family_at_full_speed_an_unknown_cell_or_the_switch_off_keep_the_pace():
    assert FreePace(0.15).speed(1.0, 0.5) == 1.0
    for free in (FreePace(None), FreePace(0.15, enabled=False)):
        assert free.speed(0.5, 0.5) == 0.5 and free.ticks == 0 and not free.free


def test_the_ceiling_is_the_highest_thing_the_limits_declare():
    assert ceiling_of(default_limits("ur5e")) == default_limits("ur5e").workspace.table_z
    cell = load_limits(EXAMPLE, variant="ur5e")
    tops = [box[5] for box in cell.workspace.keepout]
    assert tops and ceiling_of(cell) == pytest.approx(max(tops + [cell.workspace.table_z]))


def test_every_stack_gives_the_policy_node_the_cell_it_runs_in(tmp_path):
    """The sim stack: the ceiling the robot node's cell declares (the cabinet's top for a drawer task); a robot with a
    limits file: that file's; a robot without one, or the policy alone: none, so the node keeps every pace."""
    from runtime.launch import hardware_stack, policy_stack, sim_stack
    from runtime.nodes.common import config_from_dict, config_to_dict
    from runtime.nodes.policy_node import PolicyNodeConfig
    from runtime.sim_cell import cell_limits
    from sim.build import build_episode

    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["scene"], "image_size": [96, 96],
                                                        "horizons": {"action": 8}, "tasks": ["drawer_open"]}))
    node = lambda spec: config_from_dict(PolicyNodeConfig, config_to_dict(spec.config))  # noqa: E731
    sim = node(sim_stack(str(tmp_path), task="drawer_open", seed=3, dr="heavy")[1])
    world = build_episode("drawer_open", 3, "heavy", "fast").world
    assert sim.cell_ceiling_m == pytest.approx(ceiling_of(cell_limits(default_limits(world.variant.name), world)))
    assert sim.cell_ceiling_m > 0.1 and sim.free_pace  # the cabinet's top, well above the table
    hw = lambda **kw: node(hardware_stack(str(tmp_path), "10.0.0.2", {"scene": "1"}, **kw)[-1])  # noqa: E731
    assert hw().cell_ceiling_m is None
    assert hw(limits_file=str(EXAMPLE)).cell_ceiling_m == pytest.approx(ceiling_of(load_limits(EXAMPLE)))
    assert node(policy_stack(str(tmp_path))[0]).cell_ceiling_m is None


SEED = 100_004  # conftest.collected_close's


def test_a_replayed_close_at_half_speed_is_quicker_by_its_free_ticks(collected_close):
    """The collector's drawer_close replayed at the drawers' pace (0.5), through the controller and the safety layer:
    with the free pace its approach from above the cabinet plays at speed 1, and it closes the drawer sooner by those
    ticks' half periods; without, every tick is the pace's."""
    from runtime.evaluate import run_policy_episode
    from runtime.shaping import Shaping
    from tests.test_eval import Replay

    runs = {on: run_policy_episode(Replay(collected_close.action), "drawer_close", SEED, dr="heavy", speed=0.5,
                                   latency_s=0.006, shaping=Shaping(free_pace=on)) for on in (True, False)}
    assert all(out.success for out in runs.values()), {on: out.record() for on, out in runs.items()}
    assert runs[False].free_ticks == 0 and runs[True].free_ticks >= 10
    saved = runs[False].sim_seconds - runs[True].sim_seconds
    assert saved == pytest.approx(0.1 * runs[True].free_ticks, abs=0.45)  # a 0.2 s tick played in 0.1 s, each
