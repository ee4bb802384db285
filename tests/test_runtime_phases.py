"""runtime.phases: a long command run as the skills it is made of, switched by grasp cycles, each at its pace."""

import numpy as np
import pytest

from policy.pace import Pace
from runtime.phases import Phase, phase_at, phases_for

PUT = "place the blue block inside the drawer, then close the drawer"


def test_drawer_put_is_open_take_close_at_each_skills_pace():
    phases = phases_for("drawer_put", Pace({"drawer_open": 0.75, "drawer_close": 0.5}))
    assert phases == [Phase("open the drawer", 0.75), Phase(None, 1.0), Phase("close the drawer", 0.5)]
    assert [phase_at(phases, n) for n in (-1, 0, 1, 2, 5)] == [0, 0, 1, 2, 2]
    with pytest.raises(ValueError, match="'pick_place' is run as one command; phased families: drawer_put"):
        phases_for("pick_place", Pace({}))


class _Counting:
    """policy.stage.GraspCycles as a stand-in: one more cycle every `every` ticks."""

    every = 4

    def __init__(self):
        self.count, self._ticks = 0, 0

    def update(self, command, position):
        self.count = self._ticks // self.every
        self._ticks += 1
        return self.count


class _Still:
    """A bundle stand-in that holds the arm where it is and keeps the text it was given at each tick."""

    cameras, obs_horizon, image_size, execute = ("scene", "wrist"), 1, (128, 128), slice(0, 8)
    manifest = {"horizons": {"control_hz": 10.0}}

    def __init__(self):
        self.texts = []

    def embed(self, text):
        return np.frombuffer(text.encode().ljust(384)[:384], np.uint8).astype(np.float32)

    def act(self, images, proprio, emb, rng=None, stage=0, **given):
        self.texts.append(emb.astype(np.uint8).tobytes().rstrip(b" ").decode())
        chunk = np.repeat(np.asarray(proprio, np.float32)[-1:, :10], 16, axis=0)
        chunk[:, 9] = 0.0
        return chunk


def test_an_episode_switches_text_and_pace_with_the_grasp_cycles(monkeypatch):
    import policy.stage
    from runtime.evaluate import run_policy_episode

    monkeypatch.setattr(policy.stage, "GraspCycles", _Counting)
    still, times = _Still(), []
    phases = phases_for("drawer_put", Pace({"drawer_open": 0.5, "drawer_close": 0.25}))
    out = run_policy_episode(still, "drawer_put", 100_003, command=PUT, time_limit_factor=0.05, latency_s=0.006,
                             phases=phases, observer=lambda world, inst: times.append(world.time))
    assert still.texts[:12] == ["open the drawer"] * 4 + [PUT] * 4 + ["close the drawer"] * 4
    assert out.phase == 2 and out.command == PUT
    steps = np.round(np.diff(times[:13]), 3)  # ticks 1 / (10 Hz x speed) apart: 0.5, then 1, then 0.25
    np.testing.assert_allclose(steps, [0.2] * 4 + [0.1] * 4 + [0.4] * 4)
    plain = _Still()
    out = run_policy_episode(plain, "drawer_put", 100_003, command=PUT, time_limit_factor=0.02, latency_s=0.006)
    assert set(plain.texts) == {PUT} and out.phase is None
