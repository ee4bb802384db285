"""drawer_put's episodes cut into the skills their phases run (policy/phase_data.py, `sudd cut-phases`)."""

import numpy as np
import pytest

from datagen.merge import merge_datasets
from datagen.store import Dataset, ShardWriter
from datagen.workers import synthetic_episode
from policy.phase_data import cut_episode, cut_phases, parse_phase_args, phase_span
from policy.stage import GRIPPER_COLUMN

LABELS = ["open the drawer", "pick up the red block", "put the red block in the drawer", "close the drawer"]
# gripper command per step as the collector drives drawer_put: the handle taken half-open and closed (0.5 -> 1),
# let go; the object closed on (1) and let go inside (0); the handle again
SCRIPT = [(0.5, 10), (1.0, 6), (0.5, 4), (0.0, 10), (1.0, 12), (0.0, 4), (0.5, 8), (1.0, 5), (0.5, 6)]
SUBTASK = [(0, 20), (1, 12), (2, 15), (3, 18)]  # "close the drawer" begins 4 steps after the object is let go


def drawer_put_episode(seed: int, success: bool = True, subtask=SUBTASK):
    commands = np.concatenate([np.full(n, g) for g, n in SCRIPT])
    T = len(commands)
    ep = synthetic_episode("drawer_put", seed, steps=T)
    ep.action[:, GRIPPER_COLUMN] = commands
    # the fingers stop on what they hold (0.6 < the air's 0.97): every close is a grasp, not a miss
    ep.proprio[:, GRIPPER_COLUMN] = np.minimum(np.concatenate([commands[:1], commands[:-1]]), 0.6)
    ep.subtask = np.concatenate([np.full(n, k) for k, n in subtask]).astype(np.int16)
    ep.meta.update(subtasks=LABELS, instruction="put the red block in the drawer and close it", success=success,
                   label={"source": "ground_truth", "value": success})
    return ep


def test_the_closing_phase_begins_where_the_object_is_let_go():
    ep = drawer_put_episode(3)
    # commands in effect lag the recorded actions by a step: the object's release (action step 42) acts at 43
    assert phase_span(ep.action, ep.proprio, 2, last=True) == (43, len(ep))
    assert phase_span(ep.action, ep.proprio, 1, last=False) == (17, 43)
    cut = cut_episode(ep, 2)
    assert cut.meta["task"] == "drawer_close" and cut.meta["instruction"] == "close the drawer"
    assert cut.meta["phase_of"] == {"task": "drawer_put", "seed": 3, "phase": 2, "start": 43, "stop": len(ep),
                                    "instruction": "put the red block in the drawer and close it"}
    np.testing.assert_array_equal(cut.action, ep.action[43:])
    np.testing.assert_array_equal(cut.images["wrist"], ep.images["wrist"][43:])
    assert cut.time[0] == 0.0 and len(cut) == len(ep) - 43
    cut.validate()


def test_a_cut_keeps_the_release_offsets_inside_it_counted_from_its_start():
    ep = drawer_put_episode(3)
    # the object let go at action step 42 (datagen/release_offsets.py); a handle let go earlier has no entry
    ep.meta["release_offsets"] = [{"step": 42, "object": "obj0", "offset_m": [0.01, -0.02, -0.01]}]
    middle = cut_episode(ep, 1)  # steps 17..59
    assert middle.meta["release_offsets"] == [{"step": 25, "object": "obj0", "offset_m": [0.01, -0.02, -0.01]}]
    assert middle.action[25, GRIPPER_COLUMN] == 0.0 < middle.action[24, GRIPPER_COLUMN]
    closing = cut_episode(ep, 2)  # from step 43: no release of a placed object in it
    assert "release_offsets" not in closing.meta


def test_a_cycle_counted_far_from_the_subtask_is_not_cut():
    # "close the drawer" labelled 21 steps after the count says the phase began: a re-grasp miscounted
    late = [(0, 10), (1, 10), (2, 44), (3, 1)]
    assert cut_episode(drawer_put_episode(4, subtask=late), 2) == "grasp cycles and subtask labels disagree"
    ep = drawer_put_episode(5)
    ep.action[:, GRIPPER_COLUMN] = 0.5  # never closes: no phase past the first
    assert cut_episode(ep, 2) == "phase 2 never reached"


def test_cut_phases_writes_verified_closing_cycles_and_continues(tmp_path):
    with ShardWriter(tmp_path / "src", "w0") as w:
        for seed, ok in ((1, True), (2, False), (3, True)):
            w.append(drawer_put_episode(seed, ok))
        w.append(synthetic_episode("pick_place", 9))
    report = cut_phases(tmp_path / "src", tmp_path / "out", parse_phase_args(["drawer_put:2"]))
    assert report.written == {"drawer_close": 2} and report.skipped == {"not verified": 1}
    out = Dataset(tmp_path / "out")
    assert sorted((out.meta(i)["task"], out.meta(i)["seed"]) for i in range(len(out))) == \
        [("drawer_close", 1), ("drawer_close", 3)]
    again = cut_phases(tmp_path / "src", tmp_path / "out", parse_phase_args(["drawer_put:2"]))
    assert again.written == {} and again.kept_before == 2 and len(Dataset(tmp_path / "out")) == 2
    # the default cuts the opening too
    both = cut_phases(tmp_path / "src", tmp_path / "all")
    assert both.written == {"drawer_open": 2, "drawer_close": 2}


def test_the_middle_cycle_is_cut_under_its_own_text_beside_its_source(tmp_path):
    cut = cut_episode(drawer_put_episode(3), 1)
    assert cut.meta["task"] == "drawer_put"
    assert cut.meta["instruction"] == "pick up the red block and put it in the open drawer"
    # on past the object's release (43) by the prediction horizon, so the frames over the drawer are trained
    assert (cut.meta["phase_of"]["start"], cut.meta["phase_of"]["stop"]) == (17, 43 + 16)
    np.testing.assert_array_equal(cut.action, drawer_put_episode(3).action[17:59])
    unnamed = drawer_put_episode(4)
    unnamed.meta["instruction"] = "tidy up"
    assert cut_episode(unnamed, 1) == "phase 1: no object named in the instruction"
    # the cut keeps its source's family and seed: both live in one merged store, keyed apart by the phase
    with ShardWriter(tmp_path / "src", "w0") as w:
        w.append(drawer_put_episode(3))
    report = cut_phases(tmp_path / "src", tmp_path / "cut", parse_phase_args(["drawer_put:1", "drawer_put:2"]))
    assert report.written == {"drawer_put": 1, "drawer_close": 1}
    merged = merge_datasets([Dataset(tmp_path / "src"), Dataset(tmp_path / "cut")], tmp_path / "merged")
    assert sorted(merged.meta(i)["instruction"] for i in range(len(merged))) == [
        "close the drawer", "pick up the red block and put it in the open drawer",
        "put the red block in the drawer and close it"]


@pytest.mark.parametrize("arg, says", [("stack:1", "has no phases"), ("drawer_put:3", "K in 0..2"),
                                       ("drawer_put:x", "K in 0..2")])
def test_bad_phase_arguments_are_named(arg, says):
    with pytest.raises(ValueError, match=says):
        parse_phase_args([arg])


def test_offsets_are_not_measured_on_cut_phases(tmp_path):
    from datagen.views import measure_offsets

    with ShardWriter(tmp_path / "src", "w0") as w:
        w.append(drawer_put_episode(1))
    cut_phases(tmp_path / "src", tmp_path / "out")
    # its seed would rebuild a drawer_close scene that is not the one recorded
    with pytest.raises(ValueError, match="no successful drawer_close episode"):
        measure_offsets(tmp_path / "out", "drawer_close")
