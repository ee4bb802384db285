"""The policy node's settings through the running sim stack (`sudd run --sim`): how often it infers, the pace per
family, a long command run as its phases, the wrist turn and the chunks sampled per tick. Each test starts the stack
(~8 s on 2 shared cores) with an untrained `small` bundle and checks the chunks, events and exit reports."""

import numpy as np
import pytest

from stack_runs import SEED, commanded, nine_chunks

from runtime.shaping import Shaping


@pytest.fixture(scope="session")
def bundle(untrained_bundle):
    return untrained_bundle


def test_replan_every_sends_fewer_chunks_at_the_bundles_action_rate(bundle):
    """`sudd run --replan-every 4`: a chunk every 4th tick (2.5 Hz for a 10 Hz bundle), its actions still
    0.1 s apart, as the demonstrations were recorded; the arm keeps moving between chunks."""
    info, chunks, rob = nine_chunks(bundle, replan_every=4)
    assert info["hz"] == 2.5
    arrivals = np.array([t for t, _ in chunks[1:]])
    assert 0.3 < np.median(np.diff(arrivals)) < 0.8  # 0.4 s between chunks, not 0.1 s
    for _, c in chunks:
        assert np.allclose(np.diff(c.times_ns), 1e8)  # the bundle's 10 Hz
    assert np.median([(c.times_ns[0] - c.obs_time_ns) for _, c in chunks]) == 1e8
    assert rob["chunks_accepted"] >= 5 and rob["moved_rad"] > 1e-4, rob


def test_samples_are_drawn_in_a_batch_and_picked_for_coherence(bundle):
    """The node's `samples` (policy/coherence.py): K chunks a tick, the one going on from the chunk before sent."""
    info, _, chunks, reports = commanded(bundle, 9, shaping=Shaping(samples=4))
    chose, changed = reports["policy"]["coherent_picks"]
    assert chose >= 7 and 0 <= changed <= chose  # every tick after the command's first compared
    assert all(c.actions.shape == (8, 10) for _, c in chunks)  # one chunk sent, not four


@pytest.mark.parametrize("free", [False, True])
def test_a_family_at_half_speed_spaces_ticks_and_actions_twice_as_far_apart(bundle, tmp_path, free):
    """A bundle whose pace table plays pick_place at 0.5: idle at the bundle's 10 Hz, then, once a pick_place
    command is accepted (and says its family and speed), a chunk every 0.2 s whose actions are 0.2 s apart (the
    arm at half the recorded pace); the arm still moves. With the free-space pace (runtime/free_pace.py) the
    untrained policy's arm, which stays within 3 cm of the home pose (TCP 0.33 m up), is in free space above the
    bins (the sim cell's highest fixtures, 0.078 m): every chunk at the recorded pace, and the acceptance says
    where that line is."""
    import json

    from policy.testing import linked_copy

    paced = linked_copy(bundle, tmp_path / "paced")
    manifest = json.loads((paced / "manifest.json").read_text())
    (paced / "manifest.json").write_text(json.dumps({**manifest, "pace": {"pick_place": 0.5}}))
    events = []
    info, chunks, rob = nine_chunks(paced, events, shaping=Shaping(free_pace=free))
    assert info["hz"] == 10.0 and info["pace"] == {"pick_place": 0.5}
    accepted = [e for e in events if e.kind == "command_accepted"]
    assert len(accepted) == 1 and "pick_place at speed 0.5" in accepted[0].message, accepted
    assert accepted[0].values["speed"] == 0.5
    assert ("a slower pace plays at 1 above z 0.14 m" in accepted[0].message) == free, accepted[0].message
    period = 0.1 if free else 0.2
    arrivals = np.array([t for t, _ in chunks[1:]])
    assert 0.75 * period < np.median(np.diff(arrivals)) < 2 * period  # 0.2 s between chunks at half speed
    for _, c in chunks:
        assert np.allclose(np.diff(c.times_ns), period * 1e9)
    assert rob["chunks_accepted"] >= 5 and rob["moved_rad"] > 1e-4, rob


def test_phases_run_a_drawer_put_command_as_its_first_skill_at_that_skills_pace(bundle, tmp_path):
    """`sudd run` with a bundle that runs drawer_put as its phases (its manifest's `phased`, policy/phased.py;
    `--phases` forces them): a drawer_put command (one the bundle is told it was trained on) is accepted as
    drawer_put, and from the first inference the node runs phase 1 of 3, "open the drawer", at drawer_open's
    pace in the bundle's table (0.5 here): it says so, and that chunk's actions are 0.2 s apart (the free-space pace
    off: the untrained arm stays high above the cabinet, where it would play at 1)."""
    import json

    from policy.testing import linked_copy
    from sim.build import build_episode

    instruction = build_episode("drawer_put", SEED, "off", "fast").instruction
    phased = linked_copy(bundle, tmp_path / "phased")
    manifest = json.loads((phased / "manifest.json").read_text())
    (phased / "manifest.json").write_text(json.dumps({
        **manifest, "pace": {"drawer_open": 0.5}, "tasks": [*manifest["tasks"], "drawer_put", "drawer_open"],
        "phased": ["drawer_put"],
        "instructions": [*manifest["instructions"], instruction]}))
    info, events, chunks, _ = commanded(phased, 6, task="drawer_put", shaping=Shaping(free_pace=False))
    assert info["robot"]["instruction"] == instruction and info["policy"]["phased"] == ["drawer_put"]
    accepted = [e for e in events if e.kind == "command_accepted"]
    assert len(accepted) == 1 and "drawer_put at speed 1" in accepted[0].message, accepted
    phases = [e for e in events if e.kind == "policy_phase"]
    assert phases[0].message == "phase 1 of 3: 'open the drawer' at speed 0.5", phases
    assert phases[0].values == {"phase": 0.0, "speed": 0.5}
    # the untrained bundle's gripper can close and reopen before the fingers shut, which counts as a cycle:
    # later phases, if any, follow in order, each with its own text and pace
    want = ["", f"phase 2 of 3: '{instruction}' at speed 1", "phase 3 of 3: 'close the drawer' at speed 1"]
    assert [e.message for e in phases[1:]] == want[1:len(phases)]
    first = chunks[0][1]  # inferred in phase 1: its actions 1 / (10 Hz x 0.5) apart
    assert np.allclose(np.diff(first.times_ns), 2e8)


def test_the_turn_query_turns_the_wrist_of_a_stack_command_at_a_bounded_rate(bundle, tmp_path):
    """A stack command to a bundle whose turn locator always answers "turn 30 degrees" (policy.testing's constant
    locator): the policy node says the turn once (`policy_turn`, 30 degrees from the wrist's yaw at the first
    frame), and the yaws of the actions it sends turn towards it at no more than 0.6 rad/s (runtime/wrist_turn.py).
    Asked again as the wrist turns, this locator, blind to the turn, says +30 again: the target stays the equal grasp
    nearest the start yaw, so the wrist never turns more than 45 degrees from it. The untrained policy's gripper
    is held open (a first grasp cycle ends the turn)."""
    import json

    from policy.bundle import sha256_file
    from policy.grasp_axis import yaw_of
    from policy.testing import constant_turn_locator
    from runtime.wrist_turn import DEFAULT_RATE
    from sim.build import build_episode

    instruction = build_episode("stack", SEED, "off", "fast").instruction
    turned = constant_turn_locator(bundle, tmp_path / "turned", "stack", 30.0)
    manifest = json.loads((turned / "manifest.json").read_text())
    # The untrained gripper column flips open and shut, and its first grasp cycle would end the turn: keep the
    # hand open (the gripper action's scale so large that every sample reads about 0).
    with np.load(turned / "stats.npz") as z:
        stats = {k: z[k] for k in z.files}
    stats["action_scale"][9], stats["action_offset"][9] = 1e4, 0.0
    np.savez(turned / "stats.npz", **stats)
    manifest["files"]["stats.npz"] = {"bytes": (turned / "stats.npz").stat().st_size,
                                      "sha256": sha256_file(turned / "stats.npz")}
    (turned / "manifest.json").write_text(json.dumps({
        **manifest, "tasks": sorted({*manifest["tasks"], "stack"}),
        "instructions": [*manifest["instructions"], instruction]}))
    info, events, chunks, reports = commanded(turned, 30, task="stack")
    assert info["robot"]["instruction"] == instruction
    turns = [e for e in events if e.kind == "policy_turn"]
    assert len(turns) == 1 and turns[0].values["turn_deg"] == pytest.approx(30.0, abs=1e-3), turns
    assert "+30.0 deg" in turns[0].message and reports["policy"]["turn_deg"] == pytest.approx(30.0, abs=0.01)
    yaws = np.array([[yaw_of(a[3:9]) for a in c.actions] for _, c in chunks])
    start = yaws[0, 0] - DEFAULT_RATE * 0.1  # the first action is already one step of the turn along
    rel = np.degrees((yaws - start + np.pi) % (2 * np.pi) - np.pi)
    assert rel[0, -1] == pytest.approx(8 * np.degrees(DEFAULT_RATE * 0.1), abs=0.5)  # 8 steps towards +30
    assert np.all(np.abs(rel) < 45.0 + 1.0), rel.round(1)  # never past the grasp nearest the start yaw
    steps = np.abs(np.degrees((np.diff(yaws, axis=1) + np.pi) % (2 * np.pi) - np.pi))
    assert np.all(steps < np.degrees(DEFAULT_RATE * 0.1) + 0.5), steps.round(2)  # 0.6 rad/s at 10 Hz
    assert rel[:, -1].max() > 29.0  # it reached the turn asked for
