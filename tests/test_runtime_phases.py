"""runtime.phases: a long command run as the skills it is made of, switched by grasp cycles, each at its pace."""

import numpy as np
import pytest

from policy.pace import Pace
from runtime.phases import Phase, phase_at, phases_for
from runtime.shaping import Shaping

PUT = "place the blue block inside the drawer, then close the drawer"


def test_drawer_put_is_open_take_close_at_each_skills_pace():
    phases = phases_for("drawer_put", Pace({"drawer_open": 0.75, "drawer_close": 0.5}))
    # "close the drawer" is drawer_close's skill: told the cycles since it began, as drawer_close's data counts
    assert phases == [Phase("open the drawer", 0.75, family="drawer_open"), Phase(None, 1.0, family="drawer_put"),
                      Phase("close the drawer", 0.5, stage_from=2, family="drawer_close")]
    assert [phase_at(phases, n) for n in (-1, 0, 1, 2, 5)] == [0, 0, 1, 2, 2]
    with pytest.raises(ValueError, match="'pick_place' is run as one command; phased families: drawer_put"):
        phases_for("pick_place", Pace({}))


def test_a_bundle_taught_the_middle_cycles_own_text_runs_that_phase_under_it():
    from policy.phased import command_object
    from runtime.phases import Sequencer

    pace = Pace({"drawer_close": 0.5})
    plain = ["put the red block in the drawer and close it", "close the drawer"]
    assert phases_for("drawer_put", pace, plain)[1] == Phase(None, 1.0, family="drawer_put")  # never taught: the command, as before
    taught = phases_for("drawer_put", pace, plain + ["pick up the green cylinder and put it in the open drawer"])
    assert taught[1] == Phase("pick up the {obj} and put it in the open drawer", 1.0, family="drawer_put")
    seq = Sequencer(taught, lambda t: f"emb({t})", "emb(command)", PUT)
    seq.update(1)
    # the command's object, a colour the bundle never saw included
    assert seq.embedding == "emb(pick up the blue block and put it in the open drawer)" and seq.stage(1) == 1
    assert seq.describe(PUT) == "phase 2 of 3: 'pick up the blue block and put it in the open drawer' at speed 1"
    free = Sequencer(taught, lambda t: f"emb({t})", "emb(command)", "tidy the table into the cabinet")
    free.update(1)
    assert free.embedding == "emb(command)"  # no object named: the command itself
    skill = phases_for("drawer_put", pace, plain, tasks=["drawer_close", "drawer_put", "drawer_stow"])
    # taught drawer_stow: the middle phase is its skill, at its pace, counting from 0 as its data, from home
    assert skill[1] == Phase("pick up the {obj} and put it in the open drawer", 1.0, 1, from_start=True,
                             family="drawer_stow")
    assert skill[0] == taught[0] and skill[2] == taught[2]
    assert [command_object(c) for c in ("could you stow the purple bar in the drawer and close it",
                                        "store the  red block into a drawer", "open the drawer")] == \
        ["purple bar", "red block", None]


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
        self.texts, self.stages = [], []

    def embed(self, text):
        return np.frombuffer(text.encode().ljust(384)[:384], np.uint8).astype(np.float32)

    def act(self, images, proprio, emb, rng=None, stage=0, **given):
        self.texts.append(emb.astype(np.uint8).tobytes().rstrip(b" ").decode())
        self.stages.append(stage)
        chunk = np.repeat(np.asarray(proprio, np.float32)[-1:, :10], 16, axis=0)
        chunk[:, 9] = 0.0
        return chunk


def test_an_episode_switches_text_and_pace_with_the_grasp_cycles(monkeypatch):
    import policy.stage
    from runtime.evaluate import run_policy_episode

    monkeypatch.setattr(policy.stage, "GraspCycles", _Counting)
    still, times = _Still(), []
    phases = phases_for("drawer_put", Pace({"drawer_open": 0.5, "drawer_close": 0.25}))
    # the free-space pace off: the still arm stays at home, above the cabinet, where it would play at 1
    out = run_policy_episode(still, "drawer_put", 100_003, command=PUT, time_limit_factor=0.05, latency_s=0.006,
                             phases=phases, observer=lambda world, inst: times.append(world.time),
                             shaping=Shaping(free_pace=False))
    assert still.texts[:12] == ["open the drawer"] * 4 + [PUT] * 4 + ["close the drawer"] * 4
    assert still.stages[:13] == [0] * 4 + [1] * 4 + [0] * 4 + [1]  # the closing skill counts from its start
    assert out.phase == 2 and out.command == PUT
    np.testing.assert_allclose(np.diff(out.phase_starts), [0.8, 0.4], atol=1e-6)  # 4 ticks of 0.2 s, 4 of 0.1 s
    steps = np.round(np.diff(times[:13]), 3)  # ticks 1 / (10 Hz x speed) apart: 0.5, then 1, then 0.25
    np.testing.assert_allclose(steps, [0.2] * 4 + [0.1] * 4 + [0.4] * 4)
    plain = _Still()
    out = run_policy_episode(plain, "drawer_put", 100_003, command=PUT, time_limit_factor=0.02, latency_s=0.006)
    assert set(plain.texts) == {PUT} and out.phase is None and out.phase_starts == []


def test_the_sequencer_switches_only_when_the_count_selects_another_phase():
    from runtime.phases import Sequencer

    seq = Sequencer(phases_for("drawer_put", Pace({"drawer_close": 0.5})), lambda t: f"emb({t})", "emb(command)")
    assert [seq.update(n) for n in (0, 0, 1, 1, 2, 3)] == [True, False, True, False, True, False]
    assert seq.index == 2 and seq.embedding == "emb(close the drawer)" and seq.speed == 0.5
    seq.update(1)
    assert seq.embedding == "emb(command)" and seq.describe(PUT) == f"phase 2 of 3: '{PUT}' at speed 1"
    assert seq.stage(1) == 1  # the command itself: its own data's count
    seq.update(3)
    assert seq.stage(3) == 1 and seq.stage(2) == 0  # "close the drawer": cycles since it began


def test_the_phases_switch_reaches_the_policy_node_of_every_stack(tmp_path):
    import json

    from runtime.launch import hardware_stack, policy_stack, sim_stack
    from runtime.nodes.common import config_from_dict, config_to_dict
    from runtime.nodes.policy_node import PolicyNodeConfig

    (tmp_path / "manifest.json").write_text(json.dumps({"cameras": ["scene"], "image_size": [96, 96]}))
    node = lambda spec: config_from_dict(PolicyNodeConfig, config_to_dict(spec.config))  # noqa: E731
    assert node(sim_stack(str(tmp_path))[1]).phases is None  # the bundle's list unless told
    assert node(sim_stack(str(tmp_path), phases=False)[1]).phases is False
    assert node(sim_stack(str(tmp_path), phases=True)[1]).phases is True
    assert node(policy_stack(str(tmp_path), phases=True)[0]).phases is True
    assert node(hardware_stack(str(tmp_path), "10.0.0.2", {"scene": "1"}, phases=True)[-1]).phases is True


def test_the_families_run_as_phases_are_the_bundles_unless_told_and_a_bad_list_is_refused():
    from policy.phased import bundle_phased, check_phased, resolve_phased

    assert resolve_phased(("drawer_put",), None) == ("drawer_put",)
    assert resolve_phased((), None) == () and resolve_phased((), True) == ("drawer_put",)
    assert resolve_phased(("drawer_put",), False) == ()
    assert bundle_phased({"tasks": ["drawer_put"]}) == ()  # bundles before the list: none
    assert bundle_phased({"tasks": ["drawer_put"], "phased": ["drawer_put", "drawer_put"]}) == ("drawer_put",)
    with pytest.raises(ValueError, match=r"manifest phased: 'stack' has no phases; families with phases: drawer_put"):
        bundle_phased({"tasks": ["stack"], "phased": ["stack"]})
    with pytest.raises(ValueError,
                       match=r"--phased: 'drawer_put' is not one of the bundle's task families \['stack'\]"):
        check_phased(["drawer_put"], ["stack"], "--phased")
    with pytest.raises(ValueError, match="expected a list of task family names"):
        bundle_phased({"tasks": [], "phased": "drawer_put"})
