"""The data-generation episode: plan, execute, verify, retry, record — and the `sudd datagen` command."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from datagen.episode import DatagenConfig, run_episode
from datagen.planner import OfflinePlanner
from datagen.schema import ACTION_DIM, CONTROL_HZ, PERTURBED, grasp_and_release_steps, rot6d_to_matrix
from runtime.cli import main

FAST = DatagenConfig(dr="light", max_retries=2)


def test_pick_place_episode_succeeds_and_records_everything():
    data = run_episode("pick_place", 0, FAST)
    data.validate()
    meta = data.meta
    assert meta["success"] and meta["check_success"] and meta["label"] == {"value": True, "source": "ground_truth"}
    assert meta["subtasks"][0].startswith("pick up the ") and "bin" in meta["subtasks"][1]
    assert set(np.unique(data.subtask)) <= {0, 1}
    assert data.images["scene"].shape[1:] == (128, 128, 3) and data.images["wrist"].dtype == np.uint8
    assert np.allclose(np.diff(data.time), 1.0 / CONTROL_HZ, atol=0.003)
    # Actions are absolute end-effector targets with a valid 6-D rotation and a gripper command in [0, 1].
    assert data.action.shape[1] == ACTION_DIM
    R = rot6d_to_matrix(data.action[10, 3:9])
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-5)
    assert set(np.round(data.action[:, 9], 3)) <= {0.0, 1.0} | set(np.round(np.linspace(0, 1, 11), 3))
    assert data.action[:, 9].max() == 1.0, "the gripper closes during a pick"


def test_same_task_and_seed_reproduce_the_episode():
    a, b = run_episode("stack", 3, FAST), run_episode("stack", 3, FAST)
    assert np.array_equal(a.action, b.action)
    assert np.array_equal(a.images["wrist"], b.images["wrist"])


class ImpossibleCheck(OfflinePlanner):
    """The plan's check for the pick can never pass: the episode must retry, then fail honestly."""

    def plan(self, instruction, scene):
        plan = super().plan(instruction, scene)
        first = replace(plan.subtasks[0], check="def check():\n    return False\n")
        return replace(plan, subtasks=(first, *plan.subtasks[1:]))


def test_failed_check_triggers_recovery_and_retries_then_a_failure_label():
    data = run_episode("pick_place", 1, replace(FAST, max_retries=1), planner=ImpossibleCheck())
    meta = data.meta
    assert meta["retries"] == 2 and not meta["check_success"]
    assert [a["subtask"] for a in meta["attempts"]] == [0, 0]
    assert not meta["success"] and meta["label"]["value"] is False


def test_label_source_is_stated_when_the_checks_are_the_label():
    data = run_episode("drawer_open", 2, replace(FAST, label="check"))
    assert data.meta["label"] == {"value": data.meta["check_success"], "source": "check"}


def test_sudd_datagen_writes_resumes_and_reports(tmp_path, capsys):
    out = tmp_path / "data"
    args = ["datagen", "--task", "drawer_open", "--task", "drawer_close", "--episodes", "1", "--out", str(out),
            "--dr", "light", "--json"]
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["episodes"] == 2 and first["errors"] == 0
    assert main(args) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["episodes"] == 0 and again["skipped"] == 2, "a re-run resumes, nothing is duplicated"
    assert main(["datagen", "--task", "drawer_open", "--seeds", "0,5", "--out", str(out), "--dr", "light",
                 "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert (listed["skipped"], listed["episodes"]) == (1, 1), "seed 0 is there, seed 5 is new"
    assert main(["data", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 3


def test_unknown_task_in_datagen_lists_families(tmp_path, capsys):
    assert main(["datagen", "--task", "juggle", "--episodes", "1", "--out", str(tmp_path)]) == 2
    assert "pick_place" in capsys.readouterr().err


@pytest.mark.parametrize("extra, says", [(["--episodes", "1", "--seeds", "3"], "not both"),
                                         (["--seeds", "3", "--seed-offset", "5"], "not both"), ([], "either"),
                                         (["--seeds", "3,x"], "'x' is not a seed")])
def test_datagen_takes_a_count_or_a_seed_list(tmp_path, capsys, extra, says):
    assert main(["datagen", "--task", "drawer_open", "--out", str(tmp_path / "d"), *extra]) == 2
    assert says in capsys.readouterr().err and not (tmp_path / "d").exists()


def test_perturbed_place_is_recovered_by_going_back_to_the_pick():
    data = run_episode("pick_place", 6, replace(FAST, max_retries=1, perturb=1.0))
    attempts = data.meta["attempts"]
    assert [a["subtask"] for a in attempts] == [0, 1, 0, 1], attempts
    assert all("perturbed" in a["reason"] for a in attempts if a["subtask"] == 1)
    assert data.meta["retries"] == 2 and not data.meta["check_success"]
    # The recovery is in the data, labelled with the subtask being retried (never -1); the drops themselves,
    # which training must not imitate, are PERTURBED.
    assert set(np.unique(data.subtask)) == {0, 1, PERTURBED}
    assert (np.diff(data.subtask[data.subtask >= 0]) < 0).any()


def test_missed_grasp_closes_above_the_object_and_is_recovered_by_reopening_and_going_on_down():
    normal = run_episode("pick_place", 6, FAST)
    data = run_episode("pick_place", 6, replace(FAST, max_retries=1, perturb_grasp=1.0))
    attempts = data.meta["attempts"]
    assert [a["subtask"] for a in attempts] == [0, 0], attempts
    assert all(a["reason"].startswith("perturbed: gripper closed") for a in attempts)
    assert not data.meta["success"] and not data.meta["check_success"]

    def first_close(ep):
        i = int(np.argmax(ep.action[:, -1] > 0.5))
        return i, float(ep.proprio[i, 2])

    # Same grasp sample (the perturbation draws from its own stream), closed higher up the approach.
    (i, z_missed), (_, z_grasp) = first_close(data), first_close(normal)
    assert 0.005 < z_missed - z_grasp < 0.08, (z_missed, z_grasp)
    # What follows is in the data: the gripper opens again (recovery) and closes for the second try.
    grip = data.action[i:, -1] > 0.5
    reopened = int(np.argmax(~grip))
    assert reopened > 0 and grip[reopened:].any()
    # The close on air is marked as an injected failure, so it is no grasp to learn from.
    # (an action is the next step's target: the labels are one step later)
    assert data.subtask[i + 1] == PERTURBED and data.subtask[i + reopened + 1] == 0
    assert grasp_and_release_steps(data.action, data.subtask)[0] > i + reopened
    # The recovery opens where it is and goes on down the same approach (reopen()): backing off home would
    # show a retreat from the very view above the object where every other demonstration descends.
    second = i + reopened + int(np.argmax(grip[reopened:]))
    assert data.proprio[i:second, 2].max() < z_missed + 0.002 and data.proprio[second, 2] < z_missed - 0.01


def test_truncated_motion_keeps_its_start_and_ends_at_the_cut():
    from datagen.trajectory import Motion, Segment

    seg = Segment(np.linspace(0, 1, 11), np.linspace(0, 1, 11)[:, None] * np.ones(6), 0.0, "a")
    motion = Motion([seg, Segment.hold(np.ones(6), 0.5, 1.0, "b")])
    cut = motion.truncated(0.55)
    assert cut.duration == pytest.approx(0.55) and cut.labels == ["a"]
    assert np.allclose(cut.final_q, 0.55)
    assert motion.truncated(1.2).labels == ["a", "b"]
