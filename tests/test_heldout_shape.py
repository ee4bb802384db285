"""The held-out shape suite: a ball, a shape no training scene ever held, as the target (sim.tasks.base)."""

import json

import pytest

from runtime.evaluate import suite_holdout
from sim.build import task_instance
from sim.config import ConfigError
from sim.tasks import TASKS, Holdout
from sim.tasks.base import NOVEL_SHAPES, OBJECT_COLORS

HELD = {"colors": ("purple",), "shapes": ()}


def test_training_scenes_never_hold_a_novel_shape():
    for task in TASKS:
        for seed in range(60):
            inst = task_instance(task, seed, "heavy", Holdout(colors=("purple",)))
            assert not any(o.shape in NOVEL_SHAPES for o in inst.objects), (task, seed)


def test_the_suite_gives_the_target_a_ball_in_a_colour_the_data_had():
    holdout = suite_holdout("heldout_shape", HELD)
    assert holdout.split == "eval_heldout_shape" and holdout.shapes == NOVEL_SHAPES
    for task in ("pick_place", "drawer_put", "drawer_stow"):
        for seed in range(100_500, 100_520):
            inst = task_instance(task, seed, "heavy", holdout)
            target = inst.obj(inst.params["target"])
            assert target.shape == "ball" and target.color in OBJECT_COLORS and target.color != "purple"
            assert f"{target.color} ball" in inst.instruction
            assert all(o.shape != "ball" and o.color != "purple" for o in inst.objects if o is not target)
    # the colour suite is as it was: the target purple, no ball
    colour = task_instance("pick_place", 100_500, "heavy", suite_holdout("heldout", HELD))
    assert colour.obj(colour.params["target"]).color == "purple"
    assert suite_holdout("seen", HELD) == Holdout(colors=("purple",))


def test_a_family_whose_target_a_ball_cannot_be_says_so():
    with pytest.raises(ConfigError, match=r"held-out \['ball'\]: none of them can be this task's target"):
        task_instance("stack", 100_500, "heavy", suite_holdout("heldout_shape", HELD))


def test_the_collector_picks_and_places_a_ball():
    from datagen.episode import DatagenConfig, run_episode
    from sim.config import load_config

    ep = run_episode("pick_place", 100_500, load_config(DatagenConfig, {"dr": "heavy"}),
                     holdout=suite_holdout("heldout_shape", HELD))
    assert "ball" in ep.meta["instruction"] and ep.meta["success"]


def test_sudd_eval_runs_the_suite_on_the_families_a_ball_fits(untrained_bundle, tmp_path, capsys):
    from runtime.cli import main

    args = ["eval", "--policy", str(untrained_bundle), "--task", "pick_place", "--task", "stack", "--episodes", "1",
            "--no-collector", "--time-limit-factor", "0.02", "--suite", "heldout_shape", "--out", str(tmp_path)]
    assert main(args) == 0
    assert "--suite heldout_shape: not for stack" in capsys.readouterr().err
    (rec,) = [json.loads(x) for x in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert (rec["suite"], rec["task"], rec["target"]["shape"]) == ("heldout_shape", "pick_place", "ball")
    assert "| heldout_shape | pick_place | 0/1" in (tmp_path / "results.md").read_text()
