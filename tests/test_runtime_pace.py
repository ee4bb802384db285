"""runtime.pace: the arm following the policy's chunks at a fraction of the recorded pace."""

import math

import pytest

from runtime.pace import action_period_ns, check_speed


@pytest.mark.parametrize("bad", [0.0, 0.05, 1.5, math.nan, -1.0])
def test_a_speed_outside_its_range_is_refused_with_what_to_give(bad):
    with pytest.raises(ValueError, match=r"\[0.1, 1\]"):
        check_speed(bad)


def test_the_action_period_stretches_with_the_speed():
    assert action_period_ns(10.0, 1.0) == 100_000_000
    assert action_period_ns(10.0, 0.5) == 200_000_000
    with pytest.raises(ValueError):
        action_period_ns(10.0, 0.0)


def test_speed_reaches_the_policy_node_and_a_bad_one_stops_sudd_run(tmp_path, capsys):
    import json

    from runtime.cli import main
    from runtime.launch import policy_stack, sim_stack
    from runtime.nodes.common import config_from_dict, config_to_dict
    from runtime.nodes.policy_node import PolicyNodeConfig

    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["scene"], "image_size": [96, 96],
                                                        "horizons": {"action": 8}}))
    assert main(["run", "--sim", "--policy", str(tmp_path), "--speed", "0"]) == 2
    assert "[0.1, 1]" in capsys.readouterr().err
    for spec in (sim_stack(str(tmp_path), speed=0.5)[1], policy_stack(str(tmp_path), speed=0.5)[0]):
        assert config_from_dict(PolicyNodeConfig, config_to_dict(spec.config)).speed == 0.5
