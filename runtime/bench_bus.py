"""Bus benchmark: one Zenoh hop between two sessions on loopback TCP, as the runtime uses it.

    sudd bench bus            # a readable table
    sudd bench bus --json     # the figures as JSON

A hop is measured from just before `Publisher.publish` (so it includes encoding) to the subscriber's
callback (after `decode` and validation), both in this process, so one clock times both ends. Messages go
one at a time (ping-style: the next is sent when the previous has arrived) so queueing does not inflate
the figure; `frame_paced` sends a frame every 10 ms instead, which adds the receiver's wake-up from idle.
Cases: a 320x240 RGB frame through shared memory and by copy (SHM disabled on both sessions), a RobotState
and a 16-step ActionChunk; `zenoh_raw_248B_baseline` is plain Zenoh bytes of a RobotState's size with no
codec, the floor the wrapper adds to. Each figure is the median over `runs` runs of that run's percentile.
Target: frame p50 <= 0.3 ms (reference: Zenoh 1.x loopback ~75 us p50 small messages, 900 KiB frame
~0.1 ms with SHM / ~0.7 ms without, on a quiet machine).
"""

from __future__ import annotations

import os
import platform
import statistics
import threading
import time
from importlib.metadata import version

import numpy as np

from runtime import messages as m
from runtime.bus import ARM_STATE, POLICY_CHUNK, Bus, BusConfig, camera_color
from sim.camera_model import Intrinsics

FRAME_TARGET_P50_MS = 0.3
ARRIVAL_TIMEOUT_S = 2.0  # a hop not back by then counts as lost


def _frame() -> m.CameraFrame:
    rng = np.random.default_rng(0)
    return m.CameraFrame(camera_id="bench", intrinsics=Intrinsics.from_fovy(320, 240, 42.5), capture_ns=1,
                         color=rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))


def _robot_state() -> m.RobotState:
    z = np.linspace(-1, 1, 6)
    return m.RobotState(q=z, qd=z * 0.1, tcp_pose=z * 0.3, target_q=z, timestamp_ns=1)


def _chunk() -> m.ActionChunk:
    return m.ActionChunk(actions=np.zeros((16, 10)), times_ns=np.arange(1, 17) * 10_000_000, obs_time_ns=0)


def _lost_too_many(lost: int, n: int, what: str) -> None:
    """A dropped message is the DROP topics' design (a queue full under load, bus_topics.py): it is counted and
    the ping goes on; more than a tenth of them lost is a broken bus, not a busy machine."""
    if lost > max(2, n // 10):
        raise RuntimeError(f"{lost} of {n} {what} did not arrive within {ARRIVAL_TIMEOUT_S:g} s each: the "
                           "sessions are not passing messages")


def _hops(pub_bus: Bus, sub_bus: Bus, topic: str, msg: m.Message, n: int, warmup: int,
          gap_s: float) -> tuple[list[float], int]:
    """Latencies (ms) of the hops that arrived of `n` after `warmup` unrecorded ones, and how many were lost."""
    arrived, sent = threading.Event(), {}
    recv: dict[int, int] = {}
    lost = 0

    def on_msg(got: m.Message) -> None:
        recv[got.seq] = time.perf_counter_ns()
        arrived.set()

    sub = sub_bus.subscribe(topic, on_msg)
    pub = pub_bus.publisher(topic)
    if not pub.wait_matched(5.0):
        raise RuntimeError(f"no subscriber matched {topic} within 5 s")
    try:
        for _ in range(warmup + n):
            arrived.clear()
            t0 = time.perf_counter_ns()
            seq = pub.publish(msg)
            sent[seq] = t0
            if not arrived.wait(ARRIVAL_TIMEOUT_S):
                lost += 1
                _lost_too_many(lost, warmup + n, f"messages on {topic}")
            if gap_s:
                time.sleep(gap_s)
    finally:
        sub.close()
    seqs = sorted(sent)[warmup:]
    return [(recv[s] - sent[s]) * 1e-6 for s in seqs if s in recv], sum(s not in recv for s in seqs)


def _raw_hops(pub_bus: Bus, sub_bus: Bus, payload: bytes, n: int, warmup: int) -> tuple[list[float], int]:
    """The same ping with plain Zenoh puts of bytes (no codec, no checks): the floor under `_hops`."""
    arrived, recv = threading.Event(), [0]
    lost = 0

    def on_sample(sample) -> None:
        sample.payload.to_bytes()
        recv[0] = time.perf_counter_ns()
        arrived.set()

    sub = sub_bus.session.declare_subscriber("bench/raw", on_sample)
    pub = pub_bus.session.declare_publisher("bench/raw", express=True)
    out = []
    try:
        while not pub.matching_status.matching:
            time.sleep(0.005)
        for i in range(warmup + n):
            arrived.clear()
            t0 = time.perf_counter_ns()
            pub.put(payload)
            if not arrived.wait(ARRIVAL_TIMEOUT_S):
                lost += 1
                _lost_too_many(lost, warmup + n, "raw zenoh messages")
            elif i >= warmup:
                out.append((recv[0] - t0) * 1e-6)
    finally:
        sub.undeclare()
        pub.undeclare()
    return out, n - len(out)  # the recorded pings that never came back


def _percentiles(measured: list[tuple[list[float], int]]) -> dict:
    runs = [r for r, _ in measured]
    out = {}
    for q in (50, 90, 99):
        per_run = [float(np.percentile(r, q)) for r in runs]
        out[f"p{q}_ms"] = round(statistics.median(per_run), 4)
    out["p50_ms_per_run"] = [round(float(np.percentile(r, 50)), 4) for r in runs]
    out["samples_per_run"] = min(len(r) for r in runs)
    out["lost"] = sum(lost for _, lost in measured)  # dropped under load (DROP topics), not timed
    return out


def _pair(shm: bool) -> tuple[Bus, Bus]:
    a = Bus.open(BusConfig(robot="bench", shm=shm))
    b = Bus.open(BusConfig(robot="bench", listen=(), connect=a.listen_endpoints, shm=shm))
    if not b.wait_for_peers(1, 5.0):
        b.close()
        a.close()
        raise RuntimeError("bench sessions did not connect within 5 s")
    return a, b


def _codec_us(msg: m.Message, reps: int) -> dict:
    data = msg.encode()
    t = time.perf_counter()
    for _ in range(reps):
        msg.encode()
    enc = (time.perf_counter() - t) / reps
    t = time.perf_counter()
    for _ in range(reps):
        m.decode(data)
    dec = (time.perf_counter() - t) / reps
    return {"bytes": len(data), "encode_us": round(enc * 1e6, 1), "decode_us": round(dec * 1e6, 1)}


def run_bus_bench(quick: bool = False, frame_only: bool = False) -> dict:
    """Measure hop latencies and codec costs; returns a JSON-able dict (milliseconds unless named).
    `frame_only`: just the two unpaced frame hops the target is on (for `sudd bench runtime`)."""
    runs, n, warmup = (1, 40, 10) if quick else (5, 300, 30)
    t_start = time.perf_counter()
    frame, state, chunk = _frame(), _robot_state(), _chunk()
    cases = {"frame_shm": (True, camera_color("bench"), frame, 0.0),
             "frame_copy": (False, camera_color("bench"), frame, 0.0),
             "frame_paced_10ms_shm": (True, camera_color("bench"), frame, 0.010),
             "robot_state": (True, ARM_STATE, state, 0.0),
             "robot_state_paced_10ms": (True, ARM_STATE, state, 0.010),
             "action_chunk_16": (True, POLICY_CHUNK, chunk, 0.0)}
    if frame_only:
        cases = {k: v for k, v in cases.items() if k in ("frame_shm", "frame_copy")}
    result: dict = {"quick": quick, "machine": _machine(), "hop": {}, "codec": {}}
    pairs = {shm: _pair(shm) for shm in (True, False)}
    try:
        result["shm_available"] = pairs[True][0].shm_provider is not None
        for name, (shm, topic, msg, gap) in cases.items():
            count = n // 3 if gap else n
            samples = [_hops(*pairs[shm], topic, msg, count, warmup, gap) for _ in range(runs)]
            result["hop"][name] = _percentiles(samples)
        if not frame_only:
            raw = [_raw_hops(*pairs[True], b"x" * len(state.encode()), n, warmup) for _ in range(runs)]
            result["hop"]["zenoh_raw_248B_baseline"] = _percentiles(raw)
    finally:
        for a, b in pairs.values():
            b.close()
            a.close()
    reps = 50 if quick else 500
    result["codec"] = {"frame_320x240": _codec_us(frame, reps), "robot_state": _codec_us(state, reps * 10),
                       "action_chunk_16": _codec_us(chunk, reps * 10)}
    p50 = result["hop"]["frame_shm" if result["shm_available"] else "frame_copy"]["p50_ms"]
    result["frame_target_p50_ms"] = FRAME_TARGET_P50_MS
    result["frame_target_met"] = p50 <= FRAME_TARGET_P50_MS
    result["wall_s"] = round(time.perf_counter() - t_start, 1)
    return result


def _machine() -> dict:
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        affinity = os.cpu_count()
    return {"cpu_count": os.cpu_count(), "cpu_affinity": affinity, "loadavg_1min": round(os.getloadavg()[0], 2),
            "python": platform.python_version(), "zenoh": version("eclipse-zenoh"),
            "platform": platform.platform()}


def format_table(result: dict) -> str:
    mach = result["machine"]
    lines = [f"bus bench{' (quick)' if result['quick'] else ''}: {mach['cpu_affinity']}/{mach['cpu_count']} CPUs, "
             f"load {mach['loadavg_1min']}, SHM {'yes' if result['shm_available'] else 'no'}", "",
             f"{'hop (encode+put+receive+decode)':34s} {'p50 ms':>8s} {'p90 ms':>8s} {'p99 ms':>8s} {'lost':>5s}"]
    for name, h in result["hop"].items():
        lines.append(f"{name:34s} {h['p50_ms']:8.3f} {h['p90_ms']:8.3f} {h['p99_ms']:8.3f} {h['lost']:5d}")
    lines += ["", f"{'codec':34s} {'bytes':>8s} {'enc us':>8s} {'dec us':>8s}"]
    for name, c in result["codec"].items():
        lines.append(f"{name:34s} {c['bytes']:8d} {c['encode_us']:8.1f} {c['decode_us']:8.1f}")
    lines.append(f"\nframe p50 target <= {result['frame_target_p50_ms']} ms: "
                 f"{'met' if result['frame_target_met'] else 'NOT met'}")
    return "\n".join(lines)
