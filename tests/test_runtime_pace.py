"""policy.pace + runtime.pace: the arm following the policy's chunks at a fraction of the recorded pace, per task
family (the bundle's table, `--speed` on top), and the family a command belongs to."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from policy.pace import Pace, bundle_pace, check_pace_table, check_speed, parse_pace
from runtime.pace import action_period_ns, command_speed, resolve_pace
from sim.dr_config import DRConfig
from sim.tasks import TASKS, Holdout, task_names, task_of_instruction

FAMILIES = task_names()


@pytest.mark.parametrize("bad", [0.0, 0.05, 1.5, math.nan, -1.0, "fast", None])
def test_a_speed_outside_its_range_is_refused_with_what_to_give(bad):
    with pytest.raises(ValueError, match=r"\[0.1, 1\]"):
        check_speed(bad)


def test_the_action_period_stretches_with_the_speed():
    assert action_period_ns(10.0, 1.0) == 100_000_000
    assert action_period_ns(10.0, 0.5) == 200_000_000
    with pytest.raises(ValueError):
        action_period_ns(10.0, 0.0)


def test_speed_text_sets_every_family_or_the_named_ones():
    assert parse_pace("0.5", FAMILIES) == {"*": 0.5}
    assert parse_pace(" drawer_close=0.5, *=0.8 ", FAMILIES) == {"drawer_close": 0.5, "*": 0.8}
    assert parse_pace("stack=1", FAMILIES) == {"stack": 1.0}


@pytest.mark.parametrize("spec, match", [
    ("drawer_shut=0.5", r"--speed.drawer_shut: unknown task family; expected one of \['drawer_close'"),
    ("drawer_close=2", r"--speed.drawer_close '2': expected .*\[0.1, 1\]"),
    ("drawer_close=0.5,=1", r"expected F or TASK=F"),
    ("drawer_close", r"--speed 'drawer_close': expected"),
    ("", r"--speed '': expected"),
])
def test_bad_speed_text_names_what_is_wrong(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_pace(spec, FAMILIES)


def test_a_family_plays_at_its_speed_others_at_the_default():
    pace = Pace({"drawer_close": 0.5})
    assert pace.speed("drawer_close") == 0.5 and pace.speed("stack") == 1.0 and pace.speed(None) == 1.0
    assert Pace({"drawer_close": 0.5, "*": 0.8}).speed("stack") == 0.8
    assert pace.describe() == "drawer_close 0.5, others 1" and Pace().describe() == "every family 1"
    # --speed on top: a number replaces the table; named families replace theirs only
    assert pace.overridden({"*": 0.7}).table == {"*": 0.7}
    assert pace.overridden({"stack": 0.6}).table == {"drawer_close": 0.5, "stack": 0.6}
    assert pace.overridden({}) == pace


def test_the_bundle_table_is_checked_against_its_tasks():
    m = {"tasks": ["pick_place", "drawer_close"], "pace": {"drawer_close": 0.5}}
    assert bundle_pace(m).table == {"drawer_close": 0.5}
    assert bundle_pace({"tasks": ["pick_place"]}).table == {}  # bundles before the table: all at 1
    with pytest.raises(ValueError, match=r"manifest pace.stack: unknown task family"):
        bundle_pace({**m, "pace": {"stack": 0.5}})
    with pytest.raises(ValueError, match=r"manifest pace.drawer_close 0: expected"):
        bundle_pace({**m, "pace": {"drawer_close": 0}})
    with pytest.raises(ValueError, match=r"manifest pace: expected a table"):
        check_pace_table([0.5], m["tasks"], "manifest pace")
    assert resolve_pace(m, "").table == {"drawer_close": 0.5}
    assert resolve_pace(m, "0.6").table == {"*": 0.6}
    assert resolve_pace(m, "pick_place=0.9").table == {"drawer_close": 0.5, "pick_place": 0.9}


@pytest.mark.parametrize("family", FAMILIES)
def test_every_phrasing_of_a_family_maps_back_to_it(family):
    """Seen templates and unseen paraphrases of sampled instances; the closest trained instruction of a command
    is one of the former, so the runtime finds the family of any command it accepts."""
    t = TASKS[family]
    rng = np.random.default_rng(0)
    for seed in range(6):
        inst = t.sample(np.random.default_rng(seed), DRConfig(), Holdout())
        fields = t.fields(inst)
        for phrase in (*t.templates, *t.paraphrases):
            text = phrase.format(**fields)
            assert task_of_instruction(text) == family, text
            assert task_of_instruction(f"  {text.capitalize()}. ") == family
    assert command_speed(Pace({family: 0.4}), t.phrase(rng, **fields)) == (family, 0.4)


def test_text_of_no_family_plays_at_the_default_speed():
    assert task_of_instruction("wave at the camera") is None
    assert task_of_instruction("open the drawer and then dance") is None
    assert command_speed(Pace({"drawer_close": 0.5, "*": 0.9}), "wave at the camera") == (None, 0.9)
    assert command_speed(Pace(), None) == (None, 1.0)


def test_the_shipped_bundle_plays_the_drawers_slower_and_every_instruction_has_its_family():
    m = json.loads((Path(__file__).parents[1] / "policy/bundles/multitask/manifest.json").read_text())
    pace = bundle_pace(m)
    assert pace.speed("drawer_close") == 0.5 and pace.speed("drawer_open") == 0.5
    assert pace.speed("pick_place") == pace.speed("stack") == pace.speed("drawer_put") == 1.0
    families = {task_of_instruction(i) for i in m["instructions"]}
    assert families == set(m["tasks"])


def test_speed_reaches_the_policy_node_and_a_bad_one_stops_sudd_run(tmp_path, capsys):
    from runtime.cli import main
    from runtime.launch import policy_stack, sim_stack
    from runtime.nodes.common import config_from_dict, config_to_dict
    from runtime.nodes.policy_node import PolicyNodeConfig

    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["scene"], "image_size": [96, 96],
                                                        "horizons": {"action": 8}, "tasks": ["stack"]}))
    assert main(["run", "--sim", "--policy", str(tmp_path), "--speed", "0"]) == 2
    assert "[0.1, 1]" in capsys.readouterr().err
    assert main(["run", "--sim", "--policy", str(tmp_path), "--speed", "drawer_shut=0.5"]) == 2
    assert "unknown task family" in capsys.readouterr().err
    node = lambda spec: config_from_dict(PolicyNodeConfig, config_to_dict(spec.config))  # noqa: E731
    assert node(sim_stack(str(tmp_path), speed="stack=0.5")[1]).speed == "stack=0.5"
    assert node(policy_stack(str(tmp_path), speed="0.5")[0]).speed == "0.5"
