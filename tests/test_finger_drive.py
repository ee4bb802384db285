"""The 2F-85's finger drive (sim/finger_drive.py) and the collector that moves its fingers with it."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.episode import DatagenConfig, run_episode
from datagen.schema import gripper_levels
from datagen.trajectory import Motion, Segment, execute
from sim.build import build_episode
from sim.finger_drive import force_register, speed_register

GRIP = 9  # the gripper column of both the action and the proprioception (datagen/schema.py)


def _close_time(world, seconds: float = 2.0) -> float:
    """Seconds from a close command until the empty fingers pass 95 % closure (the arm held still)."""
    q = world.arm_q()
    seen = []
    execute(world, Motion([Segment.hold(q, seconds, 1.0, "close")]),
            observer=lambda w, label: seen.append((w.time, w.gripper_position())))
    t0 = seen[0][0]
    return next(t for t, closure in seen if closure > 0.95) - t0


def test_registers_map_the_2f85_ranges_and_clip():
    assert speed_register(0.02) == 0.0 and speed_register(0.15) == 1.0 and speed_register(1.0) == 1.0
    assert force_register(20.0) == 0.0 and force_register(235.0) == 1.0 and force_register(5.0) == 0.0
    assert speed_register(0.085) == pytest.approx(0.5)


def test_the_drive_closes_at_the_commanded_speed_where_the_servo_snaps():
    servo = build_episode("drawer_open", 3, "off", "fast").world  # no object between the fingers
    driven = build_episode("drawer_open", 3, "off", "fast").world
    limit = driven.model.actuator_forcerange[driven.gripper_actuator].copy()
    driven.drive_fingers(0.08, 40.0)
    # 40 N is 9 % of the 2F-85's 20-235 N range: 18 % of the model's force limit
    assert np.allclose(driven.model.actuator_forcerange[driven.gripper_actuator],
                       limit * (0.1 + 0.9 * (40.0 - 20.0) / 215.0))
    t_servo, t_driven = _close_time(servo), _close_time(driven)
    assert t_servo < 0.3
    assert 0.8 < t_driven < 1.3  # the 85 mm stroke at 80 mm/s: ~1.06 s
    assert driven.gripper_goal() == 1.0 and servo.gripper_goal() == servo.gripper_command()


@pytest.fixture(scope="module")
def picks():
    cfg = dict(dr="light", max_retries=2)
    return {mode: run_episode("pick_place", 7, DatagenConfig(gripper=mode, **cfg)) for mode in ("driver", "servo")}


def test_the_collector_records_the_levels_asked_for_not_the_ramp(picks):
    ep = picks["driver"]
    assert ep.meta["success"]
    assert gripper_levels(ep.action[:, GRIP]) == (0.0, 1.0)
    assert set(np.unique(ep.action[:, GRIP])) <= {0.0, 1.0}
    assert ep.meta["gripper"] == {"speed_m_s": 0.08, "force_n": 40.0}
    assert "gripper" not in picks["servo"].meta


def _lift_after_close(ep) -> tuple[float, float]:
    """(seconds from the first close command until the fingers stop, until the TCP first rises 1 cm)."""
    t, g = ep.time, ep.action[:, GRIP]
    i = int(np.argmax(g > 0.5))
    closure, z = ep.proprio[:, GRIP], ep.proprio[:, 2]
    settled = next(j for j in range(i + 1, len(t) - 1) if abs(closure[j + 1] - closure[j]) < 0.002)
    lifted = next(j for j in range(i, len(t)) if z[j] > z[i] + 0.01)
    return t[settled] - t[i], t[lifted] - t[i]


def test_the_collector_lifts_only_once_the_driven_fingers_have_closed(picks):
    closing, lift = _lift_after_close(picks["driver"])
    assert closing > 0.5  # the fingers took the driver's time to meet the object (0.8 s measured)
    assert lift > closing + 0.05  # and the arm held still until they had
    servo_closing, _ = _lift_after_close(picks["servo"])
    assert servo_closing < 0.4  # the instant servo's fingers: 0.3 s
