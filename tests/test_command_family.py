"""The family a command runs as: `sudd eval` judges it as the policy node does (runtime/command_family.py)."""

from pathlib import Path

import numpy as np
import pytest

from policy.pace import Pace
from runtime.command_family import command_family
from runtime.eval_report import routing_note, summarise
from runtime.evaluate import episode_command, run_policy_episode
from runtime.nodes.policy_node import judge_command
from runtime.pace import command_speed
from sim.build import build_episode, task_instance
from sim.tasks import TASKS, get_task

SHIPPED = Path(__file__).parents[1] / "policy/bundles/multitask"
FIELDS = {"obj": "green cylinder", "bin": "right", "top": "red block", "bottom": "blue cube"}


@pytest.fixture(scope="module")
def shipped():
    from policy.bundle import Bundle

    return Bundle.load(SHIPPED)


def test_the_eval_routes_a_command_as_the_policy_node_does(shipped):
    for name in TASKS:
        family = get_task(name)
        for phrase in (*family.templates, *family.paraphrases):
            text = phrase.format(**FIELDS)
            _, best, _ = judge_command(shipped, text, 0.0)
            routed = command_family(shipped, text)
            assert routed == command_speed(Pace(), best)[0], text
            if phrase in family.templates:
                assert routed == name, text  # a trained phrasing runs as its own family
    # the one unseen phrasing the shipped bundle judges another family's: the node would run it as drawer_open
    assert command_family(shipped, "push the drawer in") == "drawer_open"


def test_a_bundle_without_instructions_routes_nothing():
    class Bare:
        def task_similarity(self, text):
            return None, 0.0

    assert command_family(Bare(), "open the drawer") is None


def test_the_episode_command_is_the_one_the_episode_is_given():
    for task, seed in (("pick_place", 100_000), ("drawer_put", 100_503)):
        ep = build_episode(task, seed, "heavy", "fast")
        assert task_instance(task, seed, "heavy").record() == ep.instance.record()
        assert episode_command(task, seed, "heavy") == ep.instruction
        para = episode_command(task, seed, "heavy", paraphrase=True)
        assert para != ep.instruction and para in {p.format(**ep.task.fields(ep.instance))
                                                    for p in ep.task.paraphrases}


class Still:
    """A bundle stand-in that holds the arm where it is."""

    cameras, obs_horizon, image_size, execute = ("scene", "wrist"), 2, (128, 128), slice(1, 9)
    manifest = {"horizons": {"control_hz": 10.0}}

    def embed(self, text):
        return np.zeros(384, np.float32)

    def act(self, images, proprio, emb, rng=None, stage=0):
        return np.repeat(proprio[-1:, :10], 16, axis=0).astype(np.float32)


def test_an_episode_records_the_family_it_ran_as():
    para = episode_command("drawer_close", 100_000, "heavy", paraphrase=True)
    out = run_policy_episode(Still(), "drawer_close", 100_000, command=para, runs_as="drawer_open",
                             time_limit_factor=0.01)
    assert out.command == para and out.runs_as == "drawer_open"
    own = run_policy_episode(Still(), "drawer_close", 100_000, paraphrase=True, time_limit_factor=0.01)
    assert own.command == para and own.runs_as == "drawer_close"  # told nothing: its own family
    assert run_policy_episode(Still(), "drawer_close", 100_000, runs_as="", time_limit_factor=0.01).runs_as is None


def test_the_report_names_the_commands_run_as_another_family():
    base = {"suite": "paraphrase", "task": "drawer_close", "who": "policy", "sim_seconds": 5.0, "failure": "",
            "end": "success"}
    records = [{**base, "seed": 1, "success": True, "runs_as": "drawer_close"},
               {**base, "seed": 2, "success": True, "runs_as": "drawer_open"},
               {**base, "seed": 3, "success": False, "runs_as": "drawer_open", "end": "timeout"},
               {**base, "seed": 4, "success": False, "runs_as": None, "end": "timeout"},
               {**base, "seed": 5, "success": True}]  # recorded before runs_as: its own family
    note = routing_note(summarise(records))
    assert "paraphrase drawer_close as drawer_open: 2 (1 succeeded)" in note
    assert "paraphrase drawer_close as none: 1 (0 succeeded)" in note
    assert routing_note(summarise([records[0], records[4]])) == ""
