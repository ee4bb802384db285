"""runtime/chunk_shaper.py: the steps between the denoiser and the controller, as `sudd eval` and the node run them."""

from dataclasses import fields
from types import SimpleNamespace

import numpy as np

from policy.stage import GRIPPER_COLUMN as G
from runtime.chunk_shaper import ChunkShaper
from runtime.handle_height import BAND_M
from runtime.shaping import Shaping, shaping_of

ROT = np.array([1.0, 0, 0, 0, -1.0, 0])
NOTHING = SimpleNamespace(active=False, stage=0, points=None)  # no object query, no turn query
DT = 0.2


def _proprio(y: float, z: float, closure: float) -> np.ndarray:
    p = np.zeros((2, 16), np.float32)
    p[:, :3], p[:, 3:9], p[:, G] = (0.2, y, z), ROT, closure
    return p


def _chunks(y: float, z: float, grip: float) -> np.ndarray:
    a = np.zeros((1, 8, 10), np.float32)  # one sample
    a[0, :, :3], a[0, :, 3:9], a[0, :, G] = (0.2, y, z), ROT, grip
    return a


def _tick(s: ChunkShaper, t: float, family: str, y: float, z: float, closure: float, request: float, grip: float):
    return s.chunk(_chunks(y, z, grip), {}, _proprio(y, z, closure), 0, NOTHING, request, family, t, DT, 1.0)


def test_a_closing_that_sinks_is_held_level_with_one_word_to_the_operator():
    s = ChunkShaper(NOTHING)
    words = []
    for k, y in enumerate(np.linspace(0.31, 0.41, 6)):  # the closing skill, sinking 2 mm a tick
        out = _tick(s, (k + 1) * DT, "drawer_close", y, 0.125 - 0.002 * k, 0.8, 1.0, 1.0)
        words += s.firsts
    assert np.allclose(out[:, 2], 0.125 - BAND_M)  # kept near where the fingers closed, not 1 cm down
    assert [k for k, _ in words] == ["policy_handle_height"] and s.level.kept > 1  # said once, when it first acts
    # the same in the middle skill (an object held): the policy's heights, nothing said
    s = ChunkShaper(NOTHING)
    out = _tick(s, DT, "drawer_put", 0.31, 0.115, 0.5, 1.0, 1.0)
    assert np.allclose(out[:, 2], 0.115) and s.firsts == []


def test_fingers_shut_on_nothing_are_opened_once_with_one_word():
    """A pick_place grasp closed on air, the policy asking to stay closed: after the empty close's hold the chunks ask
    the fingers open (runtime/empty_close.py), and the operator is told once."""
    s = ChunkShaper(NOTHING)
    words, grips = [], []
    for k in range(12):  # shut on nothing since the first tick, 0.2 s apart
        out = _tick(s, (k + 1) * DT, "pick_place", 0.40, 0.03, 0.99, 1.0, 1.0)
        words += s.firsts
        grips.append(float(out[0, G]))
    assert grips[:5] == [1.0] * 5 and grips[5:] == [0.0] * 7  # 1 s after the first shut tick
    assert [k for k, _ in words] == ["policy_empty_close"] and s.empty.opened == 7


def test_every_step_off_plays_the_sample_as_it_came():
    off = Shaping(**{f.name: False for f in fields(Shaping) if f.name != "samples"})
    s = ChunkShaper(NOTHING, off)
    chunks = _chunks(0.41, 0.10, 0.0)
    out = s.chunk(chunks, {}, _proprio(0.41, 0.125, 0.8), 0, NOTHING, 1.0, "drawer_close", 1.0, DT, 1.0)
    np.testing.assert_array_equal(out, chunks[0])
    assert s.firsts == []


def test_settings_name_the_steps_and_leave_the_others_on():
    assert shaping_of({"handle_height": False, "samples": 4, "bundle": "x"}) == Shaping(handle_height=False, samples=4)
    assert shaping_of({}) == Shaping()


def test_sudd_eval_can_turn_off_each_step_and_the_policy_node_takes_each():
    """`sudd eval --no-NAME` for every step of Shaping (none forgotten when a step is added), and every step a
    field of the policy node's config, which the launcher fills from a Shaping."""
    from dataclasses import fields

    from runtime.eval_cli import STEP_FLAGS
    from runtime.nodes.policy_node import PolicyNodeConfig

    steps = {f.name for f in fields(Shaping)} - {"samples"}
    assert {name.replace("-", "_") for name, _ in STEP_FLAGS} == steps
    assert steps <= {f.name for f in fields(PolicyNodeConfig)}
