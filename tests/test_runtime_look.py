"""The goal query's look (runtime/look.py): the manifest's look pose, the views rendered from it, and an episode
that moves there, asks there, comes back and only then runs the policy."""

import numpy as np
import pytest

from policy.goal_query import GoalQuery, GoalQuerySpec, goal_query_spec, parse_look
from policy.testing import STACK, StillBundle
from runtime.look import Look
from runtime.retreat import Retreat

LOOK = (0.15, 0.08, 0.1)


def _manifest(**q):
    return {"tasks": ["stack"], "release_input": True,
            "goal_query": {"families": ["stack"], "offset_m": [0.0, 0.0, 0.0], "ticks": 3, "locator": True, **q}}


@pytest.mark.parametrize("look", [[0.1, 0.1], [0.0, 0.0, 0.5], [0.0, float("nan"), 0.0], "up", [0.1, "a", 0.0]])
def test_a_bad_look_pose_is_refused_naming_the_field(look):
    assert goal_query_spec(_manifest(look_m=list(LOOK))).look_m == LOOK
    assert goal_query_spec(_manifest()).look_m is None
    with pytest.raises(ValueError, match="goal_query.look_m"):
        goal_query_spec(_manifest(look_m=look))
    with pytest.raises(ValueError, match="needs locator true"):
        goal_query_spec(_manifest(look_m=list(LOOK), locator=False))


def test_the_look_option_parses_three_numbers_within_the_limit():
    assert parse_look("0.15,0.08,0.1") == LOOK
    for bad in ("0.1,0.1", "a,b,c", "0,0,0.4"):
        with pytest.raises(ValueError, match="--look"):
            parse_look(bad)


def test_an_episode_asks_from_the_look_pose_and_the_policy_starts_back_at_the_start():
    from runtime.evaluate import run_policy_episode

    b = StillBundle(look=LOOK)
    out = run_policy_episode(b, "pick_place", 100_003, command=STACK, time_limit_factor=0.4, latency_s=0.006)
    assert len(b.asked_at) == 3 and b.acted_at, "asked three times, then the policy ran"
    start = b.acted_at[0]
    for p in b.asked_at:  # every question at the look pose (the controller's reach, 1 cm)
        assert np.linalg.norm(p - (start + LOOK)) < 0.015
    assert np.linalg.norm(b.acted_at[0] - start) < 0.015 and np.linalg.norm(b.acted_at[-1] - start) < 0.015
    assert all(r is not None and r[3] == 1.0 for r in b.releases)  # every chunk given the look's answer
    np.testing.assert_allclose(out.goal_point, [0.1, 0.42, 0.07], atol=1e-4)
    assert out.look_gave_up is False and 1.0 < out.look_seconds < 10.0
    assert out.end != "protective_stop"


class _Query:
    """A goal query stand-in with a look pose whose answers never come (the arm never gets there)."""

    active, look, settled, point = True, True, False, None
    spec = GoalQuerySpec(("stack",), (0.0, 0.0, 0.0), 3, True, LOOK)

    def ask(self, images, proprio):
        raise AssertionError("asked away from the look pose")


def test_a_look_pose_never_reached_is_given_up_and_the_arm_sent_back():
    look = Look(_Query(), Retreat(max_seconds=1.0))
    pose = np.array([-0.13, 0.49, 0.33, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0])  # held where it is by the safety layer
    chunks = [look.chunk({}, pose[None], 0.0, 8, 0.1) for _ in range(10)]
    assert all(c is not None for c in chunks) and not look.gave_up
    np.testing.assert_allclose(chunks[0][0, :3], pose[:3] + [0.0, 0.0, 0.015], atol=1e-6)  # up first, 0.15 m/s
    assert look.chunk({}, pose[None], 0.0, 8, 0.1) is None  # a second on: given up, and the arm is at the start
    assert look.gave_up and not look.active


def test_a_query_without_a_look_pose_looks_nowhere():
    class Plain(_Query):
        look = False
        spec = GoalQuerySpec(("stack",), (0.0, 0.0, 0.0), 3, True, None)

    look = Look(Plain())
    assert not look.active and look.chunk({}, np.zeros((1, 10)), 0.0, 8, 0.1) is None
    q = GoalQuery(StillBundle(look=LOOK), STACK, "pick_place")
    assert q.look and q.release({}, np.zeros((1, 16))) is None  # nothing asked until the look asks


def test_look_views_render_the_first_view_from_the_look_pose():
    from datagen.views import look_view, scene_views
    from policy.goal_locator import locator_look

    offsets = {"grasp": np.zeros(3), "release": np.array([0.0, 0.0, 0.06])}
    home = scene_views(100_500, 2, offsets, task="stack", image_size=(32, 32))
    looked = scene_views(100_500, 2, offsets, task="stack", image_size=(32, 32), look=LOOK)
    np.testing.assert_allclose(looked["proprio"][0, :3] - home["proprio"][0, :3], LOOK, atol=2e-3)
    np.testing.assert_allclose(looked["proprio"][0, 3:9], home["proprio"][0, 3:9], atol=1e-3)  # turned alike
    np.testing.assert_array_equal(looked["points"], home["points"])  # the labels do not move with the camera
    assert not np.array_equal(looked["wrist"][0], home["wrist"][0])
    assert locator_look(looked) == pytest.approx(LOOK) and locator_look(home) is None
    with pytest.raises(ValueError, match="2 poses"):
        locator_look({"look": np.concatenate([looked["look"], home["look"]])})
    images, proprio = look_view("stack", 100_500, LOOK, image_size=(32, 32))
    np.testing.assert_allclose(proprio[0, :3], looked["proprio"][0, :3], atol=1e-4)
    assert images["wrist"].shape == (1, 32, 32, 3)
