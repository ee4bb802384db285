"""Runs of the sim stack as `sudd run --sim` starts it (real node processes, real Zenoh sessions), shared by the
runtime stack tests: a command said to it, its chunks and events collected, a clean exit checked."""

import time

from runtime import bus as B
from runtime.launch import Launcher, sim_stack

TASK, SEED = "pick_place", 0


def clean_exit(la):
    """Every node of the launcher `la` has exited, the arm at rest and nothing bypassed: the robot node's report."""
    assert la.alive() == [], la.alive()
    for p in la.procs.values():
        assert p.exitcode is not None
    rob = la.reports["robot"]
    assert rob["at_rest"] is True and rob["bypass"] == 0, rob
    assert rob["final_qd_max"] < 0.05  # read after servo_stop; at_rest above is the controller's own check
    return rob


def commanded(bundle, n: int, task: str = TASK, **policy):
    """Run the sim stack on `task`'s seed-SEED scene with these policy-node settings, say the scene's command and
    wait for `n` chunks: (every node's ready info, the StatusEvents, [(arrival, chunk)], every node's exit report)."""
    la = Launcher(sim_stack(str(bundle), task=task, seed=SEED, **policy), hub="tcp/127.0.0.1:0")
    la.start()
    events, chunks = [], []
    la.bus.subscribe(B.SAFETY_EVENT, events.append)
    la.bus.subscribe(B.POLICY_CHUNK, lambda c: chunks.append((time.monotonic(), c)))
    try:
        info = la.wait_ready(90)
        la.say(info["robot"]["instruction"], "r")
        deadline = time.monotonic() + 30
        while len(chunks) < n and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        running = len(events)
        la.shutdown("test end")
    assert len(chunks) >= n, len(chunks)
    clean_exit(la)
    # the robot node stops first, so the policy node's inputs end before it does: a clean stop, no warning
    assert not [e.message for e in events[running:] if e.kind == "policy_stale_input"]
    return info, events, chunks, la.reports


def nine_chunks(bundle, events=None, **policy):
    """Run the sim stack with these policy-node settings until 9 chunks arrived: (policy's ready info, [(arrival,
    chunk)], the robot node's exit report); `events`, a list, receives the StatusEvents."""
    info, seen, chunks, reports = commanded(bundle, 9, **policy)
    if events is not None:
        events.extend(seen)
    return info["policy"], chunks, reports["robot"]
