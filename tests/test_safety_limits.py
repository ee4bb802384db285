"""safety.limits: safe defaults per variant, TOML loading, and errors that name the field and the range."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from safety.limits import SafetyLimits, default_limits, load_limits, stop_distance_bound
from sim.config import ConfigError

EXAMPLE = Path(__file__).resolve().parents[1] / "safety" / "limits_example.toml"


@pytest.mark.parametrize("variant", ["ur5e", "ur5"])
def test_defaults_are_valid_and_conservative(variant):
    from sim.robot import get_variant

    lim = default_limits(variant)
    v = get_variant(variant)
    assert lim.variant == variant
    assert lim.joints.lower == tuple(v.joint_lower) and lim.joints.upper == tuple(v.joint_upper)
    assert all(x < y for x, y in zip(lim.joints.velocity, v.max_joint_velocity))
    assert lim.tcp.max_linear_speed == 0.25 and lim.command.max_age == 0.1
    assert lim.collision.enabled and lim.workspace.finger_clearance > 0
    assert all(lo < hi for lo, hi in zip(lim.joints.soft_lower, lim.joints.soft_upper))


def test_example_toml_loads_and_overrides_apply(tmp_path):
    lim = load_limits(EXAMPLE, "ur5e")
    assert lim.workspace.keepout  # the example declares a keep-out box
    lim2 = load_limits(EXAMPLE, "ur5e", {"tcp.max_linear_speed": 0.1, "command.max_age": 0.05})
    assert lim2.tcp.max_linear_speed == 0.1 and lim2.command.max_age == 0.05
    p = tmp_path / "cell.toml"
    p.write_text('variant = "ur5"\n[joints]\nvelocity = [0.5, 0.5, 0.5, 1.0, 1.0, 1.0]\n')
    lim3 = load_limits(p)
    assert lim3.variant == "ur5" and lim3.joints.velocity[0] == 0.5
    assert lim3.joints.upper[2] == pytest.approx(math.pi)


@pytest.mark.parametrize("overrides, match", [
    ({"tcp.max_linear_speed": 5.0}, r"tcp.max_linear_speed = 5.0 is out of range"),
    ({"joints.velocity": [1, 1, 1, 1, 1, 9]}, r"joints.velocity"),
    ({"joints.velocity": [1, 1, 1]}, r"must have 6 elements"),
    ({"tcp.max_linear_sped": 0.1}, r"did you mean 'max_linear_speed'"),
    ({"joints.jerk": [1.0] * 6}, r"joints.jerk\[0\] = 1.0 is too low"),
    ({"joints.jerk": [5000.0] * 6}, r"one 2 ms cycle at this jerk exceeds"),
    ({"joints.lower": [-7.0] * 6}, r"out of range"),
    ({"joints.upper": [6.28, 6.28, 3.2, 6.28, 6.28, 6.28]}, r"exceeds the ur5e's joint range"),
    ({"workspace.box_min": [0.0, 0.0, 0.0], "workspace.box_max": [0.5, -0.1, 0.5]}, r"box_min .* below box_max"),
    ({"workspace.keepout": [[0.1, 0.1, 0.1, 0.0, 0.2, 0.2]]}, r"keepout\[0\]"),
    ({"collision.stop_distance": 0.05}, r"stop_distance 0.05 must be below"),
    ({"variant": "ur10"}, r"variant = 'ur10' is not allowed"),
])
def test_bad_values_name_the_field(overrides, match):
    with pytest.raises(ConfigError, match=match):
        load_limits(None, None, overrides)


def test_variant_mismatch_is_an_error(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('variant = "ur5"\n')
    with pytest.raises(ConfigError, match="variant = 'ur5' but the robot is 'ur5e'"):
        load_limits(p, "ur5e")
    with pytest.raises(ConfigError, match="does not exist"):
        load_limits(tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("joints = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_limits(tmp_path / "bad.toml")


def test_stop_distance_bound_matches_the_limiter():
    from safety.joint_limits import JointLimiter

    lim = default_limits("ur5e")
    j = lim.joints
    L = JointLimiter(j.soft_lower, j.soft_upper, j.velocity, j.acceleration, j.jerk, 0.002, shrink=0.0)
    for v in (0.0, 0.1, 0.5, 1.0):
        assert stop_distance_bound(v, j.acceleration[0], j.jerk[0], 0.002) == pytest.approx(L.stop_bound(0, v, 0.0))


def test_limits_are_frozen_and_json_able():
    import json

    from sim.config import as_dict

    lim = default_limits()
    with pytest.raises(AttributeError):
        lim.variant = "ur5"  # type: ignore[misc]
    assert json.loads(json.dumps(as_dict(lim)))["tcp"]["max_linear_speed"] == 0.25
    assert isinstance(lim, SafetyLimits)
