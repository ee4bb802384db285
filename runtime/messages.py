"""Wire messages of the runtime bus: one versioned binary format, strict decoding, no pickle.

Each message is a frozen dataclass that validates itself (`_check`, run by both `encode`, as ValueError, and
`decode`, as DecodeError) and writes/reads its body with the codec of `runtime.message_codec`, which holds the
header layout, the field encodings, the size limits and DecodeError (all re-exported here).

Bodies (``str``, ``arr`` and the little-endian struct fields are encoded as `runtime.message_codec` says):

    ===============  ========================================================================
    CameraFrame      <qQHHB4d capture_ns, frame_seq, H, W, flags (1 colour | 2 depth), fx fy cx cy;
                     str camera_id; [arr u8 (H,W,3) RGB]; [arr u16 (H,W) depth mm]. 1 <= H, W <=
                     4096; intrinsics are the colour stream's at H x W; publish time = stamp_ns
    RobotState       <24dqhhd q, qd, tcp_pose, target_q (6 each), timestamp_ns, robot_mode,
                     safety_mode (UR RTDE codes), speed_scaling in [0, 1]
    GripperStatus    <ddqBBB position, target in [0, 1], timestamp_ns, is_moving, object_detected,
                     is_activated (each 0/1)
    ActionChunk      <qBH obs_time_ns, kind (1 EE [pos 3, rot6d 6, gripper 1] | 2 joint [q 6,
                     gripper 1]), n in 1..256; arr f64 (n, 10|7) actions; arr i64 (n,) times_ns,
                     strictly increasing, >= obs_time_ns
    LanguageCommand  str command_id (<= 64 chars); str text (1..1000 chars)
    StatusEvent      <B severity (0 info .. 3 critical); str kind (1..64 chars); str message (<= 1000);
                     <H n (<= 32); n x (str name, <d value)
    Telemetry        <H n (<= 64); n x (str stage, <q duration_ns >= 0)
    ===============  ========================================================================

Every float must be finite (robot state, actions, intrinsics, event values): a NaN that reaches servoJ is a
fault, so it is rejected here, before any consumer. `decode` raises only `DecodeError(reason, detail)`, with
`reason` one of REASONS.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from runtime.message_codec import (  # the header constants, limits and DecodeError: part of this module's API
    HEADER,
    MAGIC,
    MAX_BODY,
    MAX_CHUNK,
    MAX_IMAGE_SIDE,
    MAX_ITEMS,
    MAX_NAME,
    MAX_TEXT,
    REASONS,  # noqa: F401 - re-exported
    SCHEMA_VERSION,
    DecodeError,
    Message,
    Reader,
    check_finite,
    check_text,
    check_time,
    need,
)
from sim.camera_model import Intrinsics
from sim.devices import ArmState, Frame, GripperState, RobotMode, SafetyMode

SEVERITIES = ("info", "warning", "error", "critical")  # the names safety.events uses
ACTION_KINDS = {"ee": (1, 10), "joint": (2, 7)}  # kind -> (wire code, values per action)
_UR_ROBOT_MODES, _UR_SAFETY_MODES = frozenset(m.value for m in RobotMode), frozenset(m.value for m in SafetyMode)


@dataclass(frozen=True, eq=False)
class CameraFrame(Message):
    camera_id: str
    intrinsics: Intrinsics  # of the colour stream at this resolution (aligned depth shares it)
    capture_ns: int  # host monotonic time of the exposure
    color: np.ndarray | None = None  # (H, W, 3) uint8 RGB
    depth: np.ndarray | None = None  # (H, W) uint16 mm, 0 = no data
    frame_seq: int = 0  # device frame number (gaps here = camera drops; header seq gaps = bus drops)
    TYPE: ClassVar[int] = 1

    @classmethod
    def from_frame(cls, f: Frame, **hdr) -> CameraFrame:
        return cls(camera_id=f.camera_id, intrinsics=f.intrinsics, capture_ns=f.capture_ns, color=f.color,
                   depth=f.depth, frame_seq=f.seq, **hdr)

    def to_frame(self) -> Frame:
        return Frame(self.color, self.depth, self.intrinsics, self.camera_id, self.frame_seq, self.capture_ns)

    def _check(self):
        check_text("camera_id", self.camera_id, 1, MAX_NAME)
        need(self.color is not None or self.depth is not None, "bad_value", "a frame needs colour or depth")
        k = self.intrinsics
        h, w = k.height, k.width
        need(1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE, "too_large", lambda: f"image {w}x{h}")
        for name, a, dt, shape in (("color", self.color, "u1", (h, w, 3)), ("depth", self.depth, "<u2", (h, w))):
            if a is not None:
                need(isinstance(a, np.ndarray) and a.dtype == np.dtype(dt), "bad_dtype", f"{name} must be {dt}")
                need(a.shape == shape, "bad_shape", lambda: f"{name} shape {a.shape} != {shape} (from intrinsics)")
        check_finite("intrinsics", (k.fx, k.fy, k.cx, k.cy))
        need(k.fx > 0 and k.fy > 0, "bad_value", lambda: f"focal lengths must be > 0, got {k.fx}, {k.fy}")
        check_time("capture_ns", self.capture_ns)
        need(0 <= self.frame_seq < 2**64, "bad_value", "frame_seq out of range")

    def _write(self, w):
        k = self.intrinsics
        flags = (self.color is not None) | (self.depth is not None) << 1
        w.pack("<qQHHB4d", self.capture_ns, self.frame_seq, k.height, k.width, flags, k.fx, k.fy, k.cx, k.cy)
        w.text(self.camera_id)
        for a in (self.color, self.depth):
            if a is not None:
                w.array(a)

    @classmethod
    def _read(cls, r: Reader, hdr: dict):
        cap, fseq, h, w, flags, fx, fy, cx, cy = r.unpack("<qQHHB4d", "CameraFrame fields")
        need(flags in (1, 2, 3), "bad_value", lambda: f"flags = {flags}")
        need(1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE, "too_large", lambda: f"image {w}x{h}")
        cid = r.text("camera_id", 1, MAX_NAME)
        color = r.array("color", "u1", (h, w, 3)) if flags & 1 else None
        depth = r.array("depth", "<u2", (h, w)) if flags & 2 else None
        return cls(camera_id=cid, intrinsics=Intrinsics(w, h, fx, fy, cx, cy), capture_ns=cap, color=color,
                   depth=depth, frame_seq=fseq, **hdr)


@dataclass(frozen=True, eq=False)
class RobotState(Message):
    q: np.ndarray  # (6,) rad
    qd: np.ndarray  # (6,) rad/s
    tcp_pose: np.ndarray  # (6,) [x, y, z, rx, ry, rz] base frame
    target_q: np.ndarray  # (6,) rad
    timestamp_ns: int
    robot_mode: RobotMode = RobotMode.RUNNING
    safety_mode: SafetyMode = SafetyMode.NORMAL
    speed_scaling: float = 1.0
    TYPE: ClassVar[int] = 2
    _FMT: ClassVar[str] = "<24dqhhd"

    @classmethod
    def from_arm_state(cls, s: ArmState, **hdr) -> RobotState:
        return cls(q=s.q, qd=s.qd, tcp_pose=s.tcp_pose, target_q=s.target_q, timestamp_ns=s.timestamp_ns,
                   robot_mode=s.robot_mode, safety_mode=s.safety_mode, speed_scaling=s.speed_scaling, **hdr)

    def to_arm_state(self) -> ArmState:
        return ArmState(self.q, self.qd, self.tcp_pose, self.target_q, self.timestamp_ns,
                        self.robot_mode, self.safety_mode, self.speed_scaling)

    def _flat(self) -> list[float]:
        vecs = [np.asarray(v, dtype=float) for v in (self.q, self.qd, self.tcp_pose, self.target_q)]
        need(all(v.shape == (6,) for v in vecs), "bad_shape", "q, qd, tcp_pose, target_q must each be (6,)")
        return np.concatenate(vecs).tolist()

    def _check(self):  # pure-Python finiteness: 25 floats, cheaper than numpy's per-call overhead
        ok = all(map(math.isfinite, self._flat())) and math.isfinite(self.speed_scaling)
        need(ok, "non_finite", "q/qd/tcp_pose/target_q/speed_scaling has NaN/Inf")
        need(0.0 <= self.speed_scaling <= 1.0, "bad_value", "speed_scaling not in [0, 1]")
        need(self.robot_mode in _UR_ROBOT_MODES, "bad_value", lambda: f"robot_mode = {self.robot_mode}")
        need(self.safety_mode in _UR_SAFETY_MODES, "bad_value", lambda: f"safety_mode = {self.safety_mode}")
        check_time("timestamp_ns", self.timestamp_ns)

    def _write(self, w):
        w.pack(self._FMT, *self._flat(), self.timestamp_ns, self.robot_mode, self.safety_mode, self.speed_scaling)

    @classmethod
    def _read(cls, r, hdr):
        *v, ts, rm, sm, ss = r.unpack(cls._FMT, "RobotState fields")
        need(rm in _UR_ROBOT_MODES and sm in _UR_SAFETY_MODES, "bad_value", lambda: f"modes {rm}/{sm}: not UR codes")
        a = np.array(v).reshape(4, 6)
        return cls(q=a[0], qd=a[1], tcp_pose=a[2], target_q=a[3], timestamp_ns=ts, robot_mode=RobotMode(rm),
                   safety_mode=SafetyMode(sm), speed_scaling=ss, **hdr)


@dataclass(frozen=True, eq=False)
class GripperStatus(Message):
    position: float  # 0 open .. 1 closed
    target: float
    is_moving: bool
    object_detected: bool
    timestamp_ns: int
    is_activated: bool = True
    TYPE: ClassVar[int] = 3

    @classmethod
    def from_gripper_state(cls, s: GripperState, **hdr) -> GripperStatus:
        return cls(position=s.position, target=s.target, is_moving=s.is_moving, object_detected=s.object_detected,
                   timestamp_ns=s.timestamp_ns, is_activated=s.is_activated, **hdr)

    def to_gripper_state(self) -> GripperState:
        return GripperState(self.position, self.target, self.is_moving, self.object_detected, self.timestamp_ns,
                            self.is_activated)

    def _check(self):
        check_finite("position/target", (self.position, self.target))
        need(0 <= self.position <= 1 and 0 <= self.target <= 1, "bad_value", "position/target not in [0, 1]")
        check_time("timestamp_ns", self.timestamp_ns)

    def _write(self, w):
        w.pack("<ddqBBB", self.position, self.target, self.timestamp_ns, bool(self.is_moving),
               bool(self.object_detected), bool(self.is_activated))

    @classmethod
    def _read(cls, r, hdr):
        pos, tgt, ts, mv, obj, act = r.unpack("<ddqBBB", "GripperStatus fields")
        need({mv, obj, act} <= {0, 1}, "bad_value", "booleans must be 0 or 1")
        return cls(position=pos, target=tgt, is_moving=bool(mv), object_detected=bool(obj), timestamp_ns=ts,
                   is_activated=bool(act), **hdr)


@dataclass(frozen=True, eq=False)
class ActionChunk(Message):
    """N absolute targets, each with the absolute time (ns, host monotonic) at which it takes effect.

    Only the format is checked here (shape, finiteness, time order); ranges, reachability and a valid
    rotation are the safety filter's job."""

    actions: np.ndarray  # (N, 10) EE [pos 3, rot6d 6, gripper 1] or (N, 7) joint [q 6, gripper 1]
    times_ns: np.ndarray  # (N,) int64, strictly increasing
    obs_time_ns: int  # capture time of the observation the chunk was computed from
    kind: str = "ee"  # "ee" | "joint"
    TYPE: ClassVar[int] = 4

    def _check(self):
        need(self.kind in ACTION_KINDS, "bad_value", lambda: f"kind = {self.kind!r}, want one of {list(ACTION_KINDS)}")
        a, t, dim = np.asarray(self.actions), np.asarray(self.times_ns), ACTION_KINDS[self.kind][1]
        need(a.ndim == 2 and a.shape[1] == dim, "bad_shape", lambda: f"actions shape {a.shape}, want (N, {dim})")
        need(1 <= a.shape[0] <= MAX_CHUNK, "too_large", lambda: f"{a.shape[0]} actions, allowed 1..{MAX_CHUNK}")
        need(t.shape == (a.shape[0],), "bad_shape", lambda: f"times_ns shape {t.shape} != ({a.shape[0]},)")
        need(t.dtype.kind in "iu", "bad_dtype", "times_ns must be integers (ns)")
        check_finite("actions", a)
        check_time("obs_time_ns", self.obs_time_ns)
        need(bool((t >= 0).all()), "bad_value", "action times must be >= 0 ns")
        need(bool((t[1:] > t[:-1]).all()), "non_monotonic", "action times must strictly increase")
        need(int(t[0]) >= self.obs_time_ns, "non_monotonic", "first action time precedes its observation")

    def _write(self, w):
        w.pack("<qBH", self.obs_time_ns, ACTION_KINDS[self.kind][0], len(self.times_ns))
        w.array(np.asarray(self.actions, dtype="<f8"))
        w.array(np.asarray(self.times_ns, dtype="<i8"))

    @classmethod
    def _read(cls, r, hdr):
        obs, code, n = r.unpack("<qBH", "ActionChunk fields")
        kind = next((k for k, (c, _) in ACTION_KINDS.items() if c == code), None)
        need(kind is not None, "bad_value", lambda: f"action kind code {code}")
        need(1 <= n <= MAX_CHUNK, "too_large", lambda: f"{n} actions, allowed 1..{MAX_CHUNK}")
        actions = r.array("actions", "<f8", (n, ACTION_KINDS[kind][1]))
        return cls(actions=actions, times_ns=r.array("times_ns", "<i8", (n,)), obs_time_ns=obs, kind=kind, **hdr)


@dataclass(frozen=True, eq=False)
class LanguageCommand(Message):
    text: str
    command_id: str = ""
    TYPE: ClassVar[int] = 5

    def _check(self):
        check_text("command_id", self.command_id, 0, MAX_NAME)
        check_text("text", self.text, 1, MAX_TEXT)

    def _write(self, w):
        w.text(self.command_id)
        w.text(self.text)

    @classmethod
    def _read(cls, r, hdr):
        cid = r.text("command_id", 0, MAX_NAME)
        return cls(text=r.text("text", 1, MAX_TEXT), command_id=cid, **hdr)


@dataclass(frozen=True, eq=False)
class StatusEvent(Message):
    """A safety/status event; also the estop message (kind "estop", severity "critical")."""

    kind: str
    severity: str = "info"  # one of SEVERITIES
    message: str = ""
    values: dict[str, float] = field(default_factory=dict)
    TYPE: ClassVar[int] = 6

    @classmethod
    def from_safety_event(cls, ev, **hdr) -> StatusEvent:
        """From a safety.events.SafetyEvent (duck-typed); None and non-finite numbers are left out."""
        nums = {k: getattr(ev, k, None) for k in ("start", "end", "value", "limit", "count", "joint")}
        vals = {k: float(v) for k, v in nums.items() if isinstance(v, (int, float)) and math.isfinite(v)}
        return cls(kind=ev.kind, severity=ev.severity, message=ev.message[:MAX_TEXT], values=vals, **hdr)

    def _check(self):
        check_text("kind", self.kind, 1, MAX_NAME)
        need(self.severity in SEVERITIES, "bad_value", lambda: f"severity {self.severity!r} not in {SEVERITIES}")
        check_text("message", self.message, 0, MAX_TEXT)
        need(len(self.values) <= MAX_ITEMS["StatusEvent"], "too_large", lambda: f"{len(self.values)} values")
        for k in self.values:
            check_text("value name", k, 1, MAX_NAME)
        check_finite("values", np.fromiter(self.values.values(), float, len(self.values)))

    def _write(self, w):
        w.pack("<B", SEVERITIES.index(self.severity))
        w.text(self.kind)
        w.text(self.message)
        w.items(self.values, "<d")

    @classmethod
    def _read(cls, r, hdr):
        (sev,) = r.unpack("<B", "severity")
        need(sev < len(SEVERITIES), "bad_value", lambda: f"severity code {sev}")
        kind, msg = r.text("kind", 1, MAX_NAME), r.text("message", 0, MAX_TEXT)
        return cls(kind=kind, severity=SEVERITIES[sev], message=msg, values=r.items("StatusEvent", "<d"), **hdr)


@dataclass(frozen=True, eq=False)
class Telemetry(Message):
    durations_ns: dict[str, int]  # stage name -> how long the stage took this cycle (ns)
    TYPE: ClassVar[int] = 7

    def _check(self):
        need(len(self.durations_ns) <= MAX_ITEMS["Telemetry"], "too_large", lambda: f"{len(self.durations_ns)} stages")
        for k, v in self.durations_ns.items():
            check_text("stage name", k, 1, MAX_NAME)
            need(0 <= int(v) < 2**63, "bad_value", lambda: f"duration of {k!r} = {v} must be >= 0")

    def _write(self, w):
        w.items({k: int(v) for k, v in self.durations_ns.items()}, "<q")

    @classmethod
    def _read(cls, r, hdr):
        return cls(durations_ns=r.items("Telemetry", "<q"), **hdr)


MESSAGE_TYPES: dict[int, type[Message]] = {c.TYPE: c for c in (CameraFrame, RobotState, GripperStatus, ActionChunk,
                                                                LanguageCommand, StatusEvent, Telemetry)}


def decode_header(data) -> tuple[int, int, int, int]:
    """(msg_type, seq, stamp_ns, source_id), after checking magic, version, type and the body length."""
    n = len(data)
    need(n >= HEADER.size, "truncated", lambda: f"{n} bytes < {HEADER.size}-byte header")
    magic, ver, mtype, seq, stamp, src, body_len = HEADER.unpack_from(data)
    need(magic == MAGIC, "bad_magic", lambda: f"{bytes(magic)!r}")
    need(ver == SCHEMA_VERSION, "bad_version", lambda: f"schema {ver}, this build reads {SCHEMA_VERSION}")
    need(mtype in MESSAGE_TYPES, "bad_type", lambda: f"message type {mtype}")
    need(body_len <= MAX_BODY, "too_large", lambda: f"body of {body_len} bytes")
    need(n - HEADER.size >= body_len, "truncated", lambda: f"{n - HEADER.size} of {body_len} body bytes")
    need(n - HEADER.size == body_len, "oversize", lambda: f"{n - HEADER.size - body_len} bytes after the body")
    check_time("stamp_ns", stamp)
    return mtype, seq, stamp, src


def decode(data) -> Message:
    """Bytes -> a validated message (see the module docstring). Raises only DecodeError."""
    try:
        buf = memoryview(data).cast("B")
        mtype, seq, stamp, src = decode_header(buf)
        r = Reader(buf, HEADER.size)
        msg = MESSAGE_TYPES[mtype]._read(r, {"seq": seq, "stamp_ns": stamp, "source_id": src})
        need(r.pos == len(buf), "oversize", lambda: f"{len(buf) - r.pos} bytes after the {type(msg).__name__} body")
        msg._check()
        return msg
    except DecodeError:
        raise
    except (struct.error, ValueError, TypeError, OverflowError) as exc:  # defence in depth: nothing else leaks
        raise DecodeError("bad_value", f"{type(exc).__name__}: {exc}") from None
