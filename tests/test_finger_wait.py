"""runtime/finger_wait.py: the arm holds its pose while the fingers still close or open the way the chunk asks."""

import numpy as np
import pytest

from policy.stage import GRIPPER_COLUMN as G
from runtime.finger_wait import FingerWait, Wait


def step(closure: float, at=(0.4, 0.1, 0.05)) -> np.ndarray:
    """A proprio step (16,): the TCP at `at`, a fixed rot6d, the fingers' measured closure."""
    p = np.zeros(16)
    p[:3] = at
    p[3:9] = [1, 0, 0, 0, 1, 0]
    p[G] = closure
    return p


def chunk(grip: float, n: int = 8) -> np.ndarray:
    """A chunk that lifts 2 cm per action with the gripper request `grip`."""
    a = np.zeros((n, 10))
    a[:, :3] = [0.4, 0.1, 0.05] + np.outer(np.arange(1, n + 1), [0.0, 0.0, 0.02])
    a[:, 3:9] = [0, 1, 0, 1, 0, 0]
    a[:, G] = grip
    return a


def ticks(w: FingerWait, grip: float, closures, t0: float = 0.0, dt: float = 0.1) -> list[bool]:
    """Feed one chunk per tick: which were replaced by a hold."""
    out = []
    for k, c in enumerate(closures):
        a = chunk(grip)
        out.append(w.chunk(a, step(c), t=t0 + k * dt) is not a)
    return out


def test_while_the_fingers_close_the_arm_holds_its_pose_and_keeps_asking_for_the_close():
    w = FingerWait()
    assert ticks(w, 1.0, [0.1]) == [False]  # the first tick cannot tell whether they move
    out = w.chunk(chunk(1.0), step(0.19), t=0.1)
    assert np.allclose(out[:, :3], [0.4, 0.1, 0.05]) and np.allclose(out[:, 3:9], [1, 0, 0, 0, 1, 0])
    assert np.all(out[:, G] == 1.0) and w.held == 1


def test_fingers_that_stopped_on_the_object_let_the_chunk_play():
    # closing at ~0.9 / s, then on the object: a squeeze's creep (0.003 / 0.1 s) is not a close
    assert ticks(FingerWait(), 1.0, [0.3, 0.39, 0.48, 0.575, 0.578, 0.581]) == [False, True, True, True, False, False]


def test_the_rate_is_per_second_whatever_the_ticks_spacing():
    assert ticks(FingerWait(), 1.0, [0.3, 0.39, 0.48], dt=0.2) == [False, True, True]  # 0.45 / s at half pace
    assert ticks(FingerWait(), 1.0, [0.3, 0.315, 0.33], dt=0.2) == [False, False, False]  # 0.075 / s: creep


def test_an_opening_is_waited_for_too_and_a_chunk_that_turns_the_fingers_back_is_not():
    assert ticks(FingerWait(), 0.0, [0.5, 0.4, 0.3]) == [False, True, True]
    assert ticks(FingerWait(), 1.0, [0.5, 0.4, 0.3]) == [False, False, False]  # opening; the chunk asks closed
    assert ticks(FingerWait(), 0.0, [0.2, 0.3, 0.4]) == [False, False, False]  # closing; the chunk asks open


def test_a_wait_ends_after_most_s_and_a_new_one_can_start_once_the_fingers_stopped():
    w = FingerWait(Wait(most_s=0.25))
    assert ticks(w, 1.0, [0.1, 0.2, 0.3, 0.4, 0.5]) == [False, True, True, True, False]  # a finger that never stops
    assert ticks(w, 1.0, [0.5, 0.5, 0.6], t0=0.5) == [False, False, True]


def test_off_nothing_changes():
    assert ticks(FingerWait(enabled=False), 1.0, [0.1, 0.2, 0.3]) == [False, False, False]


@pytest.fixture(scope="module")
def servo_collected():
    """The pick as the shipped bundle's data recorded it: the servo collector's fingers shut in 0.1 s."""
    from datagen.episode import DatagenConfig, run_episode
    from tests.test_eval import SEED

    ep = run_episode("pick_place", SEED, DatagenConfig(dr="heavy", gripper="servo"))
    assert ep.meta["success"]
    return ep


def _height_when_closed(collected, wait: bool) -> float:
    """Replay the collector's pick through the runtime, lifting 0.2 s after the close where the collector waited
    0.6 s (as the policy did on drawer_stow seed 100502): how high over its grasp height the TCP was [m] when the
    fingers stopped on the object."""
    from runtime.evaluate import run_policy_episode
    from runtime.shaping import Shaping
    from tests.test_eval import SEED, Replay

    close = int(np.argmax(collected.action[:, G] > 0.5))
    early = np.delete(collected.action, np.arange(close + 2, close + 6), axis=0)
    seen = []
    run_policy_episode(Replay(early), "pick_place", SEED, dr="heavy", latency_s=0.006, time_limit_factor=0.4,
                       shaping=Shaping(finger_wait=wait),
                       observer=lambda world, inst: seen.append((world.tcp_pose()[2, 3], world.gripper_position(),
                                                                 world.gripper_command())))
    z, closure, cmd = np.asarray(seen).T
    k = int(np.argmax(cmd > 0.01))  # the close reaches the fingers
    stopped = k + int(np.argmax(np.abs(np.diff(closure[k:])) < 0.005))  # they stop on the object
    assert closure[stopped] > 0.3  # on the object, not before they started
    return float(z[stopped] - z[k])


def test_replayed_through_the_runtime_a_pick_that_lifts_early_waits_for_the_fingers(servo_collected):
    assert _height_when_closed(servo_collected, wait=False) > 0.03  # 80 mm/s fingers: they meet the object's top
    assert _height_when_closed(servo_collected, wait=True) < 0.015  # held until they stopped (one chunk's blend of rise)
