"""runtime/served_pause.py: a chunk's leading pause is dropped only once the arm has held still longer than the
collector's pauses, and only the part that stays where the arm is."""

import numpy as np
import pytest

from runtime.served_pause import Pause, ServedPause

TCP = np.array([0.25, 0.30, 0.13])


def proprio(pos=TCP, closure=0.75) -> np.ndarray:
    p = np.zeros(10, np.float32)
    p[:3], p[9] = pos, closure
    return p


def pause_then_push(n=8, stay=4, grip=1.0) -> np.ndarray:
    """Actions that stay at the TCP for `stay` steps, then push 1.5 cm a step along +y."""
    a = np.zeros((n, 10), np.float32)
    a[:, :3] = TCP
    a[stay:, 1] += 0.015 * (1 + np.arange(n - stay))
    a[:, 9] = grip
    return a


def held_still(sp: ServedPause, seconds: float, closure=0.75, request=1.0, dt=0.1) -> float:
    t = 0.0
    while t < seconds - 1e-9:
        sp.still_for(proprio(closure=closure), request, t)
        t += dt
    return t


def test_a_pause_not_yet_held_is_played():
    sp = ServedPause()
    t = held_still(sp, 0.8)
    a = pause_then_push()
    assert np.array_equal(sp.chunk(a, proprio(), 1.0, t), a)
    assert sp.trimmed == 0


def test_a_pause_held_longer_than_the_collectors_is_dropped_and_the_chunk_keeps_its_length():
    sp = ServedPause()
    t = held_still(sp, 1.5)
    a = pause_then_push(stay=4)
    out = sp.chunk(a, proprio(), 1.0, t)
    assert out.shape == a.shape
    assert np.array_equal(out[:4], a[4:])  # played from where it moves
    assert np.array_equal(out[4:], np.repeat(a[-1:], 4, axis=0))  # then the last action held
    assert (sp.trimmed, sp.dropped) == (1, 4)


def test_at_half_pace_the_pause_takes_twice_the_wall_time():
    sp = ServedPause()
    t = held_still(sp, 1.5)
    a = pause_then_push()
    assert np.array_equal(sp.chunk(a, proprio(), 1.0, t, speed=0.5), a)  # 1.5 s at half pace: 0.75 s of data
    t = held_still(sp, 2.6)  # the anchor kept: still since 0
    assert not np.array_equal(sp.chunk(a, proprio(), 1.0, t, speed=0.5), a)


@pytest.mark.parametrize("chunk", [
    pause_then_push(stay=0),  # moves from its first action: pushing against what holds it is not a pause
    pause_then_push(stay=8),  # stays put throughout: nothing to play from
])
def test_a_chunk_without_a_leading_pause_is_played_as_it_is(chunk):
    sp = ServedPause()
    t = held_still(sp, 3.0)
    assert np.array_equal(sp.chunk(chunk, proprio(), 1.0, t), chunk)


def test_a_let_go_after_the_pause_is_brought_forward_but_not_past():
    sp = ServedPause()
    t = held_still(sp, 2.0)
    a = pause_then_push(stay=8)
    a[3:, 9] = 0.0  # stays put and opens the fingers at the fourth action
    out = sp.chunk(a, proprio(), 1.0, t)
    assert out[0, 9] == 0.0 and sp.dropped == 3


def test_fingers_still_closing_or_the_arm_moving_is_not_holding_still():
    sp = ServedPause()
    for k in range(20):  # 2 s, the fingers closing 0.05 a tick
        sp.still_for(proprio(closure=0.05 * k), 1.0, 0.1 * k)
    a = pause_then_push()
    assert np.array_equal(sp.chunk(a, proprio(closure=1.0), 1.0, 2.0), a)
    sp = ServedPause()
    for k in range(20):  # 2 s, the arm moving 5 mm a tick
        sp.still_for(proprio(pos=TCP + [0.005 * k, 0, 0]), 1.0, 0.1 * k)
    moved = TCP + [0.1, 0, 0]
    a[:, :3] += moved - TCP
    assert np.array_equal(sp.chunk(a, proprio(pos=moved), 1.0, 2.0), a)


def test_switched_off_it_plays_every_chunk_as_it_is():
    sp = ServedPause(Pause(), enabled=False)
    t = held_still(sp, 5.0)
    a = pause_then_push()
    assert np.array_equal(sp.chunk(a, proprio(), 1.0, t), a)
