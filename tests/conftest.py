"""Shared test set-up: headless rendering must be chosen before anything imports mujoco."""

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session")
def untrained_bundle(tmp_path_factory):
    """An UNTRAINED `small` bundle (exported once per session, ~30 s) whose actions stay within 3 cm of the
    sim home pose; it lists the pick_place seed-0 instruction and a stack command as trained."""
    from runtime.bench_runtime import episode_instruction, make_test_bundle

    ins = episode_instruction("pick_place", 0)
    return make_test_bundle(tmp_path_factory.mktemp("runtime") / "bundle", [ins, "stack the red block on the blue block"])
