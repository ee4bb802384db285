"""The turn query (policy/turn_query.py): the wrist turn to grasp square to the command's object, taught modulo the
footprint's symmetry, asked on the way to the grasp and held on the policy's actions (runtime/wrist_turn.py)
until the first grasp cycle ends."""

import numpy as np
import pytest

from policy.action_frame import rot6d_of, rotations
from policy.goal_locator import locator_rows
from policy.grasp_axis import axis_label, turn_label, turn_of, wrap, yaw_of
from policy.testing import STACK, StillBundle
from policy.turn_query import TurnQuery, turn_query_spec
from policy.turn_query_measure import recorded_turn
from runtime.wrist_turn import hold_yaw

QUARTER, HALF = np.pi / 2, np.pi
DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # the TCP pointing down, yaw 0


def _about_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("period", [QUARTER, HALF])
def test_the_turn_label_reads_back_the_turn_to_the_nearest_equal_grasp(period):
    for d in np.radians([-44.0, -10.0, 0.0, 3.0, 30.0, 44.0]) * period / QUARTER:
        for tcp in (0.0, 1.3):
            label = turn_label(tcp + d, tcp, period)
            assert turn_of(label, period) == pytest.approx(d, abs=1e-5)
            # a grasp a whole period round is the same grasp: the same label
            np.testing.assert_allclose(turn_label(tcp + d + period, tcp, period), label, atol=1e-5)
    # a bar's label is the grasp-axis label it always was; a round footprint has none
    np.testing.assert_allclose(turn_label(0.4, 0.1, HALF), axis_label(0.4, 0.1, True), atol=1e-6)
    np.testing.assert_array_equal(turn_label(0.4, 0.1, 0.0), [0.0, 0.0])


def test_the_recorded_turn_is_the_collectors_yaw_at_its_first_close_wrapped_to_the_period():
    T = 12
    actions, proprio = np.zeros((T, 10), np.float32), np.zeros((T, 16), np.float32)
    proprio[:, 3:9] = rot6d_of(_about_z(0.2) @ DOWN)  # the start's yaw: 0.2 rad
    for k in range(T):
        actions[k, 3:9] = rot6d_of(_about_z(0.2 + np.radians(70.0) * min(k, 6) / 6) @ DOWN)
    assert recorded_turn(actions, proprio, QUARTER) is None  # never closes
    actions[6:, 9] = 1.0
    # 70 degrees turned: the same square grasp as 20 degrees back
    assert np.degrees(recorded_turn(actions, proprio, QUARTER)) == pytest.approx(-20.0, abs=1e-3)
    assert np.degrees(recorded_turn(actions, proprio, HALF)) == pytest.approx(70.0, abs=1e-3)
    proprio[3, 3:9] = actions[3, 3:9]  # from a frame half way there: the rest of the turn
    assert np.degrees(recorded_turn(actions, proprio, HALF, at=3)) == pytest.approx(35.0, abs=1e-3)
    assert wrap(np.radians(45.0), QUARTER) == pytest.approx(-np.pi / 4)


def _manifest(**q):
    return {"tasks": ["stack", "pick_place"], "turn_query": {"families": ["stack"], "period_deg": 90.0, **q}}


@pytest.mark.parametrize("field, bad, says", [
    ("families", ["drawer_open"], "turn_query.families"), ("families", [], "turn_query.families"),
    ("period_deg", 0, "turn_query.period_deg"), ("period_deg", 270, "turn_query.period_deg"),
    ("period_deg", True, "turn_query.period_deg"), ("min_norm", 1.5, "turn_query.min_norm"),
    ("min_norm", "high", "turn_query.min_norm")])
def test_a_manifest_turn_query_is_checked_field_by_field(field, bad, says):
    spec = turn_query_spec(_manifest())
    assert spec.families == ("stack",) and spec.period == pytest.approx(QUARTER) and spec.min_norm == 0.5
    assert turn_query_spec({"tasks": ["stack"]}) is None
    with pytest.raises(ValueError, match=says):
        turn_query_spec(_manifest(**{field: bad}))


def _proprio(wrist_yaw: float) -> np.ndarray:
    p = np.zeros((1, 16), np.float32)
    p[0, 3:9] = rot6d_of(_about_z(wrist_yaw) @ DOWN)
    return p


def test_a_sure_answer_sets_the_target_from_the_wrist_it_was_asked_at_and_an_unsure_one_does_not():
    b = StillBundle(families=("stack",), turn_deg=0.0)
    answers = iter([(0.3, 20.0), (1.0, 20.0), (0.9, 5.0), (0.2, -40.0)])  # (length, turn from the wrist then)

    def label(images, proprio, emb):
        n, d = next(answers)
        a = 4.0 * np.radians(d)
        return n * np.array([np.cos(a), np.sin(a)], np.float32)

    b.turn_label = label
    q = TurnQuery(b, STACK, "stack")
    q.ask({}, _proprio(0.1))
    assert q.active and q.target is None and q.turn is None and (q.asked, q.sure) == (1, 0)  # too short to act on
    q.ask({}, _proprio(0.1))
    assert q.target == pytest.approx(0.1 + np.radians(20.0)) and q.turn == pytest.approx(np.radians(20.0))
    q.ask({}, _proprio(0.3))  # the wrist turned on its way: the answer is from there
    assert q.target == pytest.approx(0.3 + np.radians(5.0)) and q.turn == pytest.approx(0.2 + np.radians(5.0))
    q.ask({}, _proprio(0.3))
    assert q.target == pytest.approx(0.3 + np.radians(5.0)) and (q.asked, q.sure) == (4, 2)
    assert not TurnQuery(b, STACK, "pick_place").active and not TurnQuery(b, STACK, "stack", enabled=False).active


def test_the_target_is_the_equal_grasp_nearest_the_start_yaw_whatever_the_locator_says():
    """A locator that says "+30 degrees" whatever it sees would, asked at every chunk as the wrist turns, walk the
    target round without end; the target is the grasp within half a period (45 degrees) of the start yaw."""
    b = StillBundle(families=("stack",), turn_deg=0.0)
    a = 4.0 * np.radians(30.0)
    b.turn_label = lambda images, proprio, emb: np.array([np.cos(a), np.sin(a)], np.float32)
    q = TurnQuery(b, STACK, "stack")
    targets = []
    for wrist in np.radians([0.0, 10.0, 14.0, 16.0, 40.0, -50.0]):
        q.ask({}, _proprio(0.2 + wrist))
        targets.append(np.degrees(q.target - 0.2))
    np.testing.assert_allclose(targets, [30.0, 40.0, 44.0, -44.0, -20.0, -20.0], atol=1e-6)
    assert q.turn == pytest.approx(np.radians(-20.0))


def test_the_held_yaw_is_reached_at_a_bounded_rate_and_leaves_the_rest():
    start = np.r_[0.1, 0.5, 0.3, rot6d_of(_about_z(0.3) @ DOWN)]
    target = 0.3 + np.radians(20.0)
    tilted = _about_z(-0.1) @ DOWN @ _about_z(0.0)
    tilted = tilted @ np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.1), -np.sin(0.1)], [0.0, np.sin(0.1), np.cos(0.1)]])
    chunk = np.zeros((8, 10), np.float32)
    chunk[:, :3] = np.linspace([0.1, 0.5, 0.3], [0.2, 0.5, 0.2], 8)
    chunk[:, 3:9] = rot6d_of(tilted)
    chunk[4:, 9] = 1.0
    out = hold_yaw(chunk, start, target, 0.1)
    np.testing.assert_array_equal(out[:, :3], chunk[:, :3])
    np.testing.assert_array_equal(out[:, 9], chunk[:, 9])
    yaws = [yaw_of(a[3:9]) for a in out]
    # from 0.3 rad, 0.06 rad a step (0.6 rad/s at 0.1 s), until the target 0.649 is reached (step 6)
    np.testing.assert_allclose(yaws[:3], [0.36, 0.42, 0.48], atol=1e-5)
    np.testing.assert_allclose(yaws[5:], target, atol=1e-5)
    for a in out:  # a turn about the vertical: the tilt from it is the policy's
        R = rotations(a[3:9].astype(np.float64))
        assert R[2, 2] == pytest.approx(tilted[2, 2], abs=1e-5)
    # the short way round: a target 350 degrees on is 10 degrees back
    back = hold_yaw(chunk, start, 0.3 - np.radians(10.0) + 2 * np.pi, 1.0)
    assert yaw_of(back[0, 3:9]) == pytest.approx(0.3 - np.radians(10.0), abs=1e-5)


def test_an_episode_asks_before_each_chunk_and_holds_the_turn_on_the_policys_chunks():
    from runtime.evaluate import run_policy_episode

    b = StillBundle(turn_deg=30.0)
    out = run_policy_episode(b, "pick_place", 100_003, command=STACK, time_limit_factor=0.2, latency_s=0.006)
    assert len(b.turns_asked_at) == len(b.acted_at) > 3  # asked at every chunk: the hand never closes
    assert out.turn_deg == pytest.approx(30.0, abs=0.5)
    first, last = (yaw_of(r) for r in (b.acted_rot[0], b.acted_rot[-1]))
    assert np.degrees(wrap(last - first, 2 * np.pi)) == pytest.approx(30.0, abs=2.0)  # the still policy turned
    unsure = StillBundle(turn_deg=30.0, turn_norm=0.3)
    out = run_policy_episode(unsure, "pick_place", 100_003, command=STACK, time_limit_factor=0.2, latency_s=0.006)
    assert out.turn_deg is None and len(unsure.turns_asked_at) > 3
    plain = StillBundle()
    out = run_policy_episode(plain, "pick_place", 100_003, command=STACK, time_limit_factor=0.2, latency_s=0.006)
    assert out.turn_deg is None
    first, last = (yaw_of(r) for r in (plain.acted_rot[0], plain.acted_rot[-1]))
    assert abs(np.degrees(wrap(last - first, 2 * np.pi))) < 1.0


def test_turn_rows_keep_every_view_on_the_way_to_the_first_grasp_of_one_footprint():
    n = 4
    v = {"seed": np.array([1, 1, 2, 2]), "task": np.array(["stack"] * n), "stage": np.array(["", "", "", "later"]),
         "at_home": np.array([False, False, False, False]),
         "instruction": np.array([STACK] * n), "points": np.zeros((n, 2, 3), np.float32),
         "footprint_period": np.full(n, QUARTER, np.float32)}
    out = locator_rows(v, "turn")
    assert out["seed"].tolist() == [1, 1, 2] and out["instruction"].tolist() == [STACK] * 3
    with pytest.raises(ValueError, match="one footprint period"):
        locator_rows({**v, "footprint_period": np.array([QUARTER, QUARTER, HALF, QUARTER], np.float32)}, "turn")
    with pytest.raises(ValueError, match="one footprint period"):
        locator_rows({**v, "footprint_period": np.zeros(n, np.float32)}, "turn")  # round: no turn to learn
