"""Wire format: every message round-trips; anything else is rejected with DecodeError and a named reason.

The fuzz tests are the point: a payload off the network must never crash a consumer with anything but
DecodeError, and must never yield a message carrying NaN/Inf to the policy or the arm.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from runtime import messages as m
from sim.camera_model import Intrinsics
from sim.devices import ArmState, Frame, GripperState, RobotMode, SafetyMode

K = Intrinsics(8, 6, 10.0, 11.0, 3.5, 2.5)
RNG = np.random.default_rng(0)


def samples() -> list[m.Message]:
    v = np.linspace(-1.0, 1.0, 6)
    return [
        m.CameraFrame(camera_id="wrist", intrinsics=K, capture_ns=5, frame_seq=9,
                      color=RNG.integers(0, 256, (6, 8, 3), dtype=np.uint8),
                      depth=RNG.integers(0, 2**16, (6, 8), dtype=np.uint16)),
        m.CameraFrame(camera_id="scene", intrinsics=K, capture_ns=5, depth=np.zeros((6, 8), np.uint16)),
        m.RobotState(q=v, qd=v * 0.1, tcp_pose=v * 0.5, target_q=v + 0.01, timestamp_ns=7,
                     robot_mode=RobotMode.IDLE, safety_mode=SafetyMode.PROTECTIVE_STOP, speed_scaling=0.5),
        m.GripperStatus(position=0.25, target=1.0, is_moving=True, object_detected=False, timestamp_ns=3),
        m.ActionChunk(actions=RNG.normal(size=(4, 10)), times_ns=np.array([10, 20, 30, 45]), obs_time_ns=10),
        m.ActionChunk(actions=RNG.normal(size=(1, 7)), times_ns=np.array([100]), obs_time_ns=0, kind="joint"),
        m.LanguageCommand(text="put the red block in the bin ✓", command_id="cmd-1"),
        m.StatusEvent(kind="estop", severity="critical", message="operator", values={"joint": 2.0, "v": -0.5}),
        m.Telemetry(durations_ns={"camera": 1200, "policy": 8_000_000, "safety": 0}),
    ]


def fields_equal(a: m.Message, b: m.Message) -> bool:
    if type(a) is not type(b):
        return False
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.shape == y.shape
                    and np.array_equal(x, y)):
                return False
        elif x != y:
            return False
    return True


def all_floats_finite(msg: m.Message) -> bool:
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        if isinstance(v, Intrinsics):
            v = [v.fx, v.fy, v.cx, v.cy]
        elif isinstance(v, dict):
            v = list(v.values())
        arr = np.asarray(v) if v is not None and not isinstance(v, str) else None
        if arr is not None and arr.dtype.kind == "f" and not np.isfinite(arr).all():
            return False
    return True


def encode_unchecked(msg: m.Message, **header) -> bytes:
    """Encode without the validation `encode` does: how a buggy or hostile peer would."""
    cls = type(msg)
    original = cls.__dict__["_check"]
    cls._check = lambda self: None
    try:
        return msg.encode(**header)
    finally:
        cls._check = original


def reason_of(data: bytes) -> str:
    with pytest.raises(m.DecodeError) as info:
        m.decode(data)
    assert info.value.detail or info.value.reason in ("bad_magic",)
    return info.value.reason


@pytest.mark.parametrize("msg", samples(), ids=lambda x: type(x).__name__)
def test_round_trip(msg):
    data = msg.encode(seq=42, stamp_ns=123_456, source_id=2**64 - 1)
    got = m.decode(data)
    assert fields_equal(got, dataclasses.replace(msg, seq=42, stamp_ns=123_456, source_id=2**64 - 1))
    assert got.encode() == data  # canonical: re-encoding gives the same bytes
    assert m.decode(bytearray(data)).seq == 42 and m.decode(memoryview(data)).seq == 42


def test_decoded_arrays_are_read_only_views():
    frame = m.decode(samples()[0].encode())
    assert not frame.color.flags.writeable and frame.color.dtype == np.uint8 and frame.depth.dtype == np.uint16


def test_device_conversions():
    v = np.arange(6.0)
    arm = ArmState(v, v, v, v, 5, RobotMode.RUNNING, SafetyMode.REDUCED, 0.3)
    back = m.decode(m.RobotState.from_arm_state(arm).encode()).to_arm_state()
    assert back.safety_mode == SafetyMode.REDUCED and np.array_equal(back.q, v) and back.speed_scaling == 0.3
    cam = Frame(np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.uint16), K, "wrist", 12, 99)
    back_cam = m.decode(m.CameraFrame.from_frame(cam).encode()).to_frame()
    assert (back_cam.seq, back_cam.capture_ns, back_cam.intrinsics) == (12, 99, K)
    assert np.array_equal(back_cam.depth, cam.depth)
    grip = GripperState(0.5, 1.0, True, True, 9, True)
    assert m.decode(m.GripperStatus.from_gripper_state(grip).encode()).to_gripper_state() == grip


def test_status_event_from_safety_event():
    ev = type("Ev", (), dict(kind="workspace", severity="warning", message="clamped", start=1.0, end=None,
                             value=0.7, limit=float("inf"), count=3, joint=None))()
    got = m.decode(m.StatusEvent.from_safety_event(ev).encode())
    assert got.values == {"start": 1.0, "value": 0.7, "count": 3.0} and got.severity == "warning"


def _header(data: bytes, **changes) -> bytes:
    names = ("magic", "version", "msg_type", "seq", "stamp_ns", "source_id", "body_len")
    values = dict(zip(names, m.HEADER.unpack_from(data)))
    values.update(changes)
    return m.HEADER.pack(*values.values()) + data[m.HEADER.size:]


def test_header_rejections():
    data = samples()[2].encode()
    assert reason_of(b"XUDD" + data[4:]) == "bad_magic"
    assert reason_of(_header(data, version=2)) == "bad_version"
    assert reason_of(_header(data, msg_type=99)) == "bad_type"
    assert reason_of(data[:-1]) == "truncated"
    assert reason_of(data[:10]) == "truncated"
    assert reason_of(b"") == "truncated"
    assert reason_of(data + b"\0") == "oversize"
    assert reason_of(_header(data, body_len=2**31)) == "too_large"
    assert reason_of(_header(data, stamp_ns=-1)) == "bad_value"
    # a valid body under another type's header: the body cannot parse as that type
    assert reason_of(_header(data, msg_type=m.ActionChunk.TYPE)) in ("truncated", "oversize", "bad_value",
                                                                     "bad_dtype", "too_large", "bad_shape")


def test_shape_and_size_rejections():
    frame = samples()[0]
    data = bytearray(frame.encode())
    # the colour array header says (6, 8, 3); claim (6, 7, 3): shape mismatch with the frame's H x W
    at = data.index(struct.pack("<BB3I", 1, 3, 6, 8, 3))
    data[at:at + 14] = struct.pack("<BB3I", 1, 3, 6, 7, 3)
    assert reason_of(bytes(data)) == "bad_shape"
    big = dataclasses.replace(frame, intrinsics=Intrinsics(5000, 6, 1.0, 1.0, 0.0, 0.0), color=None,
                              depth=np.zeros((6, 5000), np.uint16))
    assert reason_of(encode_unchecked(big)) == "too_large"
    with pytest.raises(ValueError, match="too_large"):
        big.encode()
    chunk = m.ActionChunk(actions=np.zeros((257, 10)), times_ns=np.arange(1, 258), obs_time_ns=0)
    assert reason_of(encode_unchecked(chunk)) == "too_large"
    wrong_dim = m.ActionChunk(actions=np.zeros((3, 9)), times_ns=np.arange(1, 4), obs_time_ns=0)
    assert reason_of(encode_unchecked(wrong_dim)) == "bad_shape"
    long_text = m.LanguageCommand(text="x" * 1001)
    assert reason_of(encode_unchecked(long_text)) == "too_large"
    assert reason_of(encode_unchecked(m.LanguageCommand(text=""))) == "bad_value"
    many = m.Telemetry(durations_ns={f"s{i}": 1 for i in range(65)})
    assert reason_of(encode_unchecked(many)) == "too_large"
    bad_utf8 = bytearray(m.LanguageCommand(text="abc").encode())
    bad_utf8[-1] = 0xFF
    assert reason_of(bytes(bad_utf8)) == "bad_text"


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_rejected(bad):
    v = np.zeros(6)
    cases = [
        m.RobotState(q=np.r_[bad, v[1:]], qd=v, tcp_pose=v, target_q=v, timestamp_ns=1),
        m.RobotState(q=v, qd=v, tcp_pose=v, target_q=v, timestamp_ns=1, speed_scaling=bad),
        m.ActionChunk(actions=np.full((2, 10), bad), times_ns=np.array([1, 2]), obs_time_ns=0),
        m.CameraFrame(camera_id="c", intrinsics=Intrinsics(8, 6, bad, 1.0, 0.0, 0.0), capture_ns=0,
                      color=np.zeros((6, 8, 3), np.uint8)),
        m.GripperStatus(position=bad, target=0.0, is_moving=False, object_detected=False, timestamp_ns=0),
        m.StatusEvent(kind="k", values={"x": bad}),
    ]
    for msg in cases:
        with pytest.raises(ValueError, match="non_finite"):
            msg.encode()
        assert reason_of(encode_unchecked(msg)) == "non_finite", msg


def test_action_times_must_increase():
    a = np.zeros((3, 10))
    for times, obs in (([10, 10, 20], 0), ([10, 30, 20], 0), ([10, 20, 30], 11)):
        chunk = m.ActionChunk(actions=a, times_ns=np.array(times), obs_time_ns=obs)
        with pytest.raises(ValueError, match="non_monotonic"):
            chunk.encode()
        assert reason_of(encode_unchecked(chunk)) == "non_monotonic"
    wrapped = m.ActionChunk(actions=a[:2], times_ns=np.array([2**63 - 1, -2**63]), obs_time_ns=0)
    assert reason_of(encode_unchecked(wrapped)) == "bad_value"  # would wrap a naive diff


def test_enum_and_range_rejections():
    v = np.zeros(6)
    state = m.RobotState(q=v, qd=v, tcp_pose=v, target_q=v, timestamp_ns=1)
    for bad in (dict(robot_mode=42), dict(safety_mode=0), dict(speed_scaling=1.5), dict(timestamp_ns=-5)):
        assert reason_of(encode_unchecked(dataclasses.replace(state, **bad))) == "bad_value", bad
    grip = bytearray(samples()[3].encode())
    grip[-1] = 2  # is_activated must be 0/1
    assert reason_of(bytes(grip)) == "bad_value"
    event = bytearray(m.StatusEvent(kind="k").encode())
    event[m.HEADER.size] = 9  # severity code past "critical"
    assert reason_of(bytes(event)) == "bad_value"


def test_encode_rejects_wrong_types():
    with pytest.raises(ValueError, match="bad_dtype"):
        m.CameraFrame(camera_id="c", intrinsics=K, capture_ns=0, color=np.zeros((6, 8, 3), np.float32)).encode()
    with pytest.raises(ValueError, match="bad_shape"):
        m.CameraFrame(camera_id="c", intrinsics=K, capture_ns=0, color=np.zeros((8, 6, 3), np.uint8)).encode()
    with pytest.raises(ValueError):
        m.LanguageCommand(text="hi").encode(seq=-1)


# --- fuzzing ---------------------------------------------------------------------------------------------
VALID = [msg.encode(seq=1, stamp_ns=2, source_id=3) for msg in samples()]
FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _must_not_crash(data: bytes) -> None:
    try:
        msg = m.decode(data)
    except m.DecodeError as exc:
        assert exc.reason in m.REASONS
        return
    assert all_floats_finite(msg)
    assert m.decode(msg.encode()) is not None  # whatever decodes also re-encodes


@FUZZ
@given(st.binary(max_size=600))
def test_fuzz_random_bytes(data):
    _must_not_crash(data)


@FUZZ
@given(st.binary(max_size=400), st.sampled_from(sorted(m.MESSAGE_TYPES)))
def test_fuzz_random_body_under_valid_header(body, mtype):
    _must_not_crash(m.HEADER.pack(m.MAGIC, m.SCHEMA_VERSION, mtype, 1, 2, 3, len(body)) + body)


@st.composite
def mutated(draw):
    data = bytearray(draw(st.sampled_from(VALID)))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(("flip", "set", "cut", "insert", "nan")))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and data:
            data[at] = draw(st.integers(0, 255))
        elif op == "cut":
            del data[at:at + draw(st.integers(1, 16))]
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "nan" and len(data) >= at + 8:
            data[at:at + 8] = struct.pack("<d", draw(st.sampled_from([float("nan"), float("inf"), -1e308])))
    if draw(st.booleans()) and len(data) >= m.HEADER.size:  # keep the length field consistent: go deeper
        struct.pack_into("<I", data, m.HEADER.size - 4, len(data) - m.HEADER.size)
    return bytes(data)


@FUZZ
@given(mutated())
def test_fuzz_mutated_valid_encodings(data):
    _must_not_crash(data)
