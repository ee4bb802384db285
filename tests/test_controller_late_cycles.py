"""Late control cycles (a loaded host): the commanded stream keeps the plan's clock.

The safety filter's stream moves one period of motion per step. A cycle that wakes k periods late steps the
filter through the k periods it missed first (ControllerConfig.catch_up_periods), so the arm stays on its
plan instead of falling behind and being caught up faster than planned. Lockstep: a skipped cycle is a rig
step with no controller cycle, as a real UR's servo period passes without a command.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_controller_sim import chunk, line, make


def _follow(skip_every: int, **cfg):
    """TCP error to a 10 cm/s line (m, per moving cycle), skipping every `skip_every`-th cycle (0: none)."""
    rig, loop, p0, R = make(**cfg)
    t0 = rig.now_ns() * 1e-9
    path = line(p0, t0 + 0.5)
    every = round(0.4 / rig.control_period)
    err, tcp = [], []
    for k in range(round(3.0 / rig.control_period)):
        if k % every == 0:
            assert loop.submit(chunk(rig.now_ns(), path, R)), loop.drain_events()
        if not (skip_every and k % skip_every == skip_every - 1):
            loop.cycle()
        rig.step(1)
        s = rig.arm.state()
        t = s.timestamp_ns * 1e-9
        if t0 + 0.7 < t < t0 + 2.5:
            err.append(np.linalg.norm(s.tcp_pose[:3] - path(t)))
            tcp.append(s.tcp_pose[:3])
    kinds = {e.kind for e in loop.drain_events()}
    n = 5  # cycles: the TCP's speed over 10 ms
    speeds = np.linalg.norm(np.diff(np.array(tcp)[::n], axis=0), axis=1) / (n * rig.control_period)
    return np.array(err), speeds, kinds


def test_a_late_cycle_steps_the_periods_it_missed_and_the_arm_keeps_its_plan():
    on_time, v_on, _ = _follow(0)
    late, v_late, kinds = _follow(3)  # a third of the cycles one period late
    no_catch_up, v_lag, _ = _follow(3, catch_up_periods=0)
    print(f"\nTCP error p50 / max (mm): on time {1e3 * np.median(on_time):.2f} / {1e3 * on_time.max():.2f}; "
          f"1 in 3 late {1e3 * np.median(late):.2f} / {1e3 * late.max():.2f}; "
          f"without the catch-up {1e3 * np.median(no_catch_up):.2f} / {1e3 * no_catch_up.max():.2f}")
    assert np.median(late) < 1.5 * np.median(on_time) + 5e-4 and late.max() < 0.01
    assert np.median(no_catch_up) > 3 * np.median(late)  # what the catch-up is for: stepping once lags
    assert v_late.max() < 1.2 * v_on.max()  # no faster than planned
    assert not kinds & {"velocity", "acceleration", "jerk"}, kinds  # every substep within the limits


@pytest.mark.parametrize("late_by", [3, 30])
def test_a_long_gap_is_a_stall_not_a_burst(late_by):
    """Past catch_up_periods the filter steps at most that many periods: the jump the arm is sent is bounded."""
    rig, loop, p0, R = make(catch_up_periods=5)
    t0 = rig.now_ns() * 1e-9
    path = line(p0, t0, speed=0.2)
    loop.submit(chunk(rig.now_ns(), path, R))
    sent = []
    for k in range(600):
        if k == 400:
            rig.step(late_by)  # the host stalls: late_by periods with no cycle
        sent.append(np.array(loop.cycle().result.q))
        rig.step(1)
    steps = np.max(np.abs(np.diff(sent, axis=0)), axis=1)  # steps[399]: from cycle 399 to the late 400
    typical = np.median(steps[300:399])
    assert steps[399] <= (min(late_by, 5) + 1) * typical * 1.3 + 1e-6
    assert steps[399] > min(late_by, 5) * typical * 0.7  # it did step through the missed periods
