"""runtime/eval_trace.py: a failed episode's tick-by-tick CSV says what the arm did and what it was asked to do."""

import csv

import numpy as np
import pytest

from policy.stage import GRIPPER_COLUMN
from runtime.eval_trace import COLUMNS, Trace
from runtime.evaluate import run_policy_episode
from tests.test_eval import SEED, Replay, collected  # noqa: F401 (a fixture)


def test_a_trace_records_every_tick_the_chunks_sent_and_changes_nothing(collected, tmp_path):  # noqa: F811
    trace = Trace()
    seen = []
    out = run_policy_episode(Replay(collected.action), "pick_place", SEED, dr="heavy", latency_s=0.006, trace=trace,
                             observer=lambda world, inst: seen.append(world.tcp_pose()[:3, 3].copy()))
    plain = []
    run_policy_episode(Replay(collected.action), "pick_place", SEED, dr="heavy", latency_s=0.006,
                       observer=lambda world, inst: plain.append(world.tcp_pose()[:3, 3].copy()))
    assert out.success and np.array_equal(np.asarray(seen), np.asarray(plain))  # it read the sim, never moved it
    rows = trace.rows
    assert len(rows) == len(seen) and [r["t"] for r in rows] == sorted(r["t"] for r in rows)
    assert np.allclose([[r[f"tcp_{k}"] for k in "xyz"] for r in rows], 100 * np.asarray(seen), atol=0.06)
    # the replay's chunk k starts at the collector's action k: the trace keeps what was sent, in centimetres
    sent = [r for r in rows if r.get("chunk") == "accepted"]
    assert len(sent) == out.chunks
    for k in (0, len(sent) // 2, len(sent) - 1):
        assert [sent[k][f"aim_{c}"] for c in "xyz"] == pytest.approx(100 * collected.action[k, :3], abs=0.06)
        assert sent[k]["aim_grip"] == pytest.approx(collected.action[k, GRIPPER_COLUMN], abs=0.006)
    # the fingers close on the named object, carry it up and let it go in the bin
    held = [r for r in rows if r["holds_target"]]
    assert rows[0]["holds_target"] == 0 and held and rows[-1]["holds_target"] == 0
    assert min(r["closure"] for r in held) > rows[0]["closure"] + 0.3
    assert max(r["target_z"] for r in held) > rows[0]["target_z"] + 5.0
    assert "drawer" not in rows[0]  # pick_place has no drawer: blank, not a 0 that reads "shut"
    path = trace.save(tmp_path / "traces" / "t.csv")
    with path.open() as f:
        back = list(csv.DictReader(f))
    assert tuple(back[0]) == COLUMNS and len(back) == len(rows) and back[0]["drawer"] == ""


def test_events_are_kept_on_the_tick_they_came_in():
    trace = Trace()
    trace.events(["ignored before any tick"])
    assert trace.rows == []
    trace.rows.append({"t": 0.1})
    trace.events([])
    trace.events(["gripper_open_held", "velocity_scaled"])
    trace.events(["velocity_scaled"])
    assert trace.rows[-1]["events"] == "gripper_open_held;velocity_scaled;velocity_scaled"
