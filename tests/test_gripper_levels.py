"""The gripper channel's levels: the half-open pre-shape of the drawer families reaches the fingers, the binary
channel of a bundle that records none is unchanged, and the levels come from the data through the bundle."""

import numpy as np
import pytest

from datagen.schema import gripper_levels
from runtime.controller import ControllerConfig, with_bundle_levels
from runtime.controller.gripper import GripperChannel
from safety import default_limits
from sim.build import build_episode
from sim.config import ConfigError
from sim.twins.rig import SimRig


@pytest.fixture(scope="module")
def rig():
    ep = build_episode("drawer_open", 3, "off", "fast")
    r = SimRig(ep.world, "lockstep")
    r.gripper.activate()
    return r


def _feed(channel, values):
    """What each value sent (True closed / False not closed / None nothing) and the target it left."""
    out = []
    for k, v in enumerate(values):
        sent = channel.update(v, 10.0 * k, True, None)
        out.append((sent, None if channel.level is None else channel.levels[channel.level]))
    return out


def test_three_levels_reach_the_half_open_pre_shape(rig):
    channel = GripperChannel(rig.gripper, default_limits("ur5e"), ControllerConfig(gripper_levels=(0.0, 0.5, 1.0),
                                                                                reopen_empty_grasp=False))
    got = _feed(channel, [0.0, 0.45, 0.72, 0.85, 0.75, 0.55, 0.28, 0.1])
    # bands: 0.2..0.3 between open and half, 0.7..0.8 between half and closed
    assert got == [(False, 0.0), (False, 0.5), (None, 0.5), (True, 1.0), (None, 1.0), (False, 0.5), (None, 0.5),
                   (False, 0.0)]
    assert channel.commands == 5
    channel.update(0.5, 100.0, True, None)
    assert rig.gripper.state().target == pytest.approx(0.5, abs=0.01)  # a position move, not a grasp
    assert channel.closed is False


def test_a_bundle_without_levels_keeps_the_binary_channel(rig):
    channel = GripperChannel(rig.gripper, default_limits("ur5e"), ControllerConfig(reopen_empty_grasp=False))
    assert channel.levels == (0.0, 1.0)
    got = _feed(channel, [0.0, 0.5, 0.59, 0.61, 0.45, 0.39])
    assert [s for s, _ in got] == [False, None, None, True, None, False]


def test_inside_a_band_a_far_level_moves_to_the_nearer_neighbour(rig):
    channel = GripperChannel(rig.gripper, default_limits("ur5e"), ControllerConfig(gripper_levels=(0.0, 0.5, 1.0),
                                                                                reopen_empty_grasp=False))
    assert _feed(channel, [0.0, 0.75]) == [(False, 0.0), (False, 0.5)]  # from open, 0.75 is at most half-closed
    assert _feed(GripperChannel(rig.gripper, default_limits("ur5e"), ControllerConfig(gripper_levels=(0.0, 0.5, 1.0))),
                 [0.25]) == [(None, None)]  # nothing standing yet: a value inside a band asks for nothing
    assert _feed(channel, [float("nan"), float("inf")]) == [(None, 0.5), (None, 0.5)]  # not a number: no change


def test_levels_come_from_the_bundle_unless_the_controller_names_them():
    manifest = {"data": {"gripper_levels": [0.0, 0.5, 1.0]}}
    assert with_bundle_levels(ControllerConfig(), manifest).gripper_levels == (0.0, 0.5, 1.0)
    assert with_bundle_levels(ControllerConfig(), {"data": {}}).gripper_levels is None  # binary
    mine = ControllerConfig(gripper_levels=(0.0, 1.0))
    assert with_bundle_levels(mine, manifest) is mine
    with pytest.raises(ConfigError, match=r"data.gripper_levels = \[0.5, 1.0\].*from 0.0 \(open\) to 1.0"):
        with_bundle_levels(ControllerConfig(), {"data": {"gripper_levels": [0.5, 1.0]}})
    with pytest.raises(ConfigError, match="gripper_levels = \\[0.0, 0.7, 0.5, 1.0\\]: expected increasing"):
        ControllerConfig(gripper_levels=(0.0, 0.7, 0.5, 1.0)).validate()


def test_the_data_levels_are_the_held_commands_not_the_ramps():
    ramp = np.linspace(0.0, 1.0, 5)  # a few steps between levels, each value under 1 % of the steps
    drawer = np.concatenate([np.full(40, 0.5), ramp, np.full(60, 1.0), np.full(400, 0.0)])
    assert gripper_levels([drawer, np.zeros(50)]) == (0.0, 0.5, 1.0)
    assert gripper_levels(np.concatenate([np.zeros(300), ramp, np.ones(200)])) == (0.0, 1.0)
    assert gripper_levels(np.zeros(10)) == (0.0, 1.0)  # open and closed always
