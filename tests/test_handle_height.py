"""runtime/handle_height.py: while the fingers hold a drawer's handle, the arm keeps the height they closed at."""

import numpy as np
import pytest

from policy.stage import CLOSED, GRIPPER_COLUMN as G
from runtime.handle_height import BAND_M, HANDLE_FAMILIES, HandleHeight
from runtime.phases import Sequencer, phases_for
from policy.pace import Pace


def _chunk(z: np.ndarray, grip: np.ndarray) -> np.ndarray:
    a = np.zeros((len(z), 10), np.float32)
    a[:, 0], a[:, 1], a[:, 2], a[:, G] = 0.3, np.linspace(0.4, 0.5, len(z)), z, grip
    a[:, 3], a[:, 7] = 1.0, 1.0  # some rotation, kept
    return a


def test_a_sinking_pull_is_kept_at_the_height_the_fingers_closed_at():
    h = HandleHeight()
    sink = _chunk(0.125 - 0.001 * np.arange(8), np.full(8, 1.0))
    out = h.chunk(sink, "drawer_open", command=1.0, closure=0.78, tcp_z=0.125)  # held: 0.22 short of the request
    assert h.height == pytest.approx(0.125) and h.kept == 1
    np.testing.assert_allclose(out[:, 2], np.maximum(sink[:, 2], 0.125 - BAND_M), atol=1e-7)
    assert out[:, 2].min() == pytest.approx(0.125 - BAND_M)
    np.testing.assert_array_equal(np.delete(out, 2, axis=1), np.delete(sink, 2, axis=1))  # only the height moved
    # the next tick: the TCP sank a little, the height noted stays the one the fingers closed at
    rise = _chunk(0.124 + 0.002 * np.arange(8), np.full(8, 1.0))
    out = h.chunk(rise, "drawer_open", command=1.0, closure=0.88, tcp_z=0.124)  # a handle on the pads: 0.86-0.88
    assert out[:, 2].max() == pytest.approx(0.125 + BAND_M) and h.height == pytest.approx(0.125)


def test_rows_from_the_first_opening_on_are_the_policys():
    h = HandleHeight()
    grip = np.array([1.0, 1.0, 1.0, 0.2, 0.0, 0.0, 1.0, 1.0])  # let go at row 3: the lift after it is left alone
    a = _chunk(np.full(8, 0.10), grip)
    out = h.chunk(a, "drawer_close", command=1.0, closure=0.8, tcp_z=0.125)
    np.testing.assert_allclose(out[:3, 2], 0.125 - BAND_M, atol=1e-7)
    np.testing.assert_array_equal(out[3:], a[3:])


def test_nothing_changes_unless_a_handle_is_held():
    a = _chunk(0.10 - 0.002 * np.arange(8), np.full(8, 1.0))
    # an object, not a handle: drawer_stow's hold goes down into the drawer
    h = HandleHeight()
    assert h.chunk(a, "drawer_stow", 1.0, 0.5, 0.125) is a and h.kept == 0
    # the fingers shut on nothing, or where a part-closed request put them: no hold
    h = HandleHeight()
    assert h.chunk(a, "drawer_open", 1.0, 0.95, 0.125) is a and h.height is None
    assert h.chunk(a, "drawer_open", 0.8, 0.78, 0.125) is a and h.height is None
    # still open or opening: no hold either
    assert h.chunk(a, "drawer_open", CLOSED - 0.01, 0.2, 0.125) is a and h.height is None
    # turned off: the policy's heights
    h = HandleHeight(enabled=False)
    assert h.chunk(a, "drawer_open", 1.0, 0.78, 0.125) is a and h.kept == 0
    # a chunk already within the band is returned as it was
    h = HandleHeight()
    level = _chunk(np.full(8, 0.125), np.full(8, 1.0))
    assert h.chunk(level, "drawer_open", 1.0, 0.78, 0.125) is level and h.kept == 0


def test_each_hold_notes_its_own_height():
    h = HandleHeight()
    a = _chunk(np.full(8, 0.10), np.full(8, 1.0))
    h.chunk(a, "drawer_open", 1.0, 0.8, 0.125)
    h.chunk(a, "drawer_open", 0.0, 0.8, 0.15)  # told open: the hold is over
    assert h.height is None
    h.chunk(a, "drawer_open", 1.0, 0.8, 0.12)
    assert h.chunk(a, "drawer_open", 1.0, 0.97, 0.12) is a and h.height is None  # shut on nothing: none held
    out = h.chunk(a, "drawer_open", 1.0, 0.8, 0.11)
    assert h.height == pytest.approx(0.11) and out[:, 2].min() == pytest.approx(0.11 - BAND_M)


def test_drawer_puts_phases_name_their_skills_family():
    """The handle height acts in drawer_put's first and last phases (the handle's), not in its middle one."""
    phases = phases_for("drawer_put", Pace({}), tasks=("drawer_open", "drawer_close", "drawer_put"))
    seq = Sequencer(phases, lambda t: np.zeros(384, np.float32), np.zeros(384, np.float32), "put the red block in "
                    "the drawer and close it")
    families = []
    for cycles in range(3):
        seq.update(cycles)
        families.append(seq.family)
    assert families[0] in HANDLE_FAMILIES and families[2] in HANDLE_FAMILIES
    assert families[1] not in HANDLE_FAMILIES


SEED = 100_004  # conftest.collected_close's


@pytest.mark.parametrize("keep", [True, False])
def test_a_push_that_sinks_closes_the_drawer_only_when_held_level(collected_close, keep):
    """The collector's push replayed with its height sinking 3 cm over the hold (the denoiser's chunks sink as they
    push), through the controller and the safety layer. Kept level, the drawer shuts as the collector's did; not
    kept, the fingers press the handle down, the drawer sticks on its rails and the push stalls."""
    from runtime.evaluate import run_policy_episode
    from runtime.shaping import Shaping
    from tests.test_eval import Replay

    actions = np.array(collected_close.action, np.float32)
    hold = np.flatnonzero(actions[:, G] >= CLOSED)
    actions[hold, 2] -= np.linspace(0.0, 0.03, len(hold), dtype=np.float32)
    out = run_policy_episode(Replay(actions), "drawer_close", SEED, dr="heavy", latency_s=0.006,
                             time_limit_factor=0.4, shaping=Shaping(handle_height=keep))
    if keep:
        assert out.success and out.handle_levels > 0, out.record()
    else:
        assert not out.success and out.end == "timeout" and out.handle_levels == 0, out.record()
        assert out.drawer_end > 0.3  # left open: the push stalled
