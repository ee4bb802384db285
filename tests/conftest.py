"""Shared test set-up: headless rendering must be chosen before anything imports mujoco."""

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
pytest.register_assert_rewrite("stack_runs")  # its checks of a stack's exit fail with the values, as a test's do


@pytest.fixture(scope="session")
def untrained_bundle(tmp_path_factory):
    """An UNTRAINED `small` bundle (exported once per session, ~30 s) whose actions stay within 3 cm of the
    sim home pose; it lists the pick_place seed-0 instruction and a stack command as trained."""
    from runtime.bench_runtime import episode_instruction, make_test_bundle

    ins = episode_instruction("pick_place", 0)
    return make_test_bundle(tmp_path_factory.mktemp("runtime") / "bundle", [ins, "stack the red block on the blue block"])


@pytest.fixture(scope="module")
def loose_offsets():
    """An untrained tiny head's swapped grasp points lie ~0.4 m from the synthetic release points, past the
    offset a trained one is allowed (refused, as test_the_measure_refuses_... checks): allow it in a module."""
    with pytest.MonkeyPatch.context() as mp:
        for module in ("policy.goal_query", "policy.goal_query_measure", "policy.bundle_manifest"):
            mp.setattr(f"{module}.MAX_OFFSET_M", 2.0, raising=False)
        yield


@pytest.fixture(scope="session")
def collected_close():
    """The collector's verified drawer_close episode of seed 100004 under heavy DR: its actions, replayed through
    the controller and the safety layer, are a push that shuts the drawer (tests of the steps that act on it)."""
    from datagen.episode import DatagenConfig, run_episode

    ep = run_episode("drawer_close", 100_004, DatagenConfig(dr="heavy"))
    assert ep.meta["success"]
    return ep
