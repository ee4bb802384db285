"""The runtime bus: typed `runtime.messages` over Zenoh 1.x, with per-topic QoS and counted bad input.

Why Zenoh: one peer-to-peer pub/sub that is ~75 us a hop on loopback, carries camera frames through shared
memory, and is what rmw_zenoh (ROS 2) speaks, so a ROS tool can join later without a bridge. Why a wrapper:
every topic has one message type and one QoS decided here (an estop is never dropped, an old frame always
is), every payload is decoded and validated once at the edge, and bad payloads are counted per reason
instead of reaching the policy or the arm.

Key layout (``<robot>`` = BusConfig.robot; topics are given relative, e.g. ``bus.publisher("arm/state")``):

    ====================================  ===============  ========================================
    key                                   message          QoS
    ====================================  ===============  ========================================
    sudd/<robot>/camera/<name>/color      CameraFrame      image: DATA, drop, SHM for large frames
    sudd/<robot>/camera/<name>/depth      CameraFrame      image (depth-only frames)
    sudd/<robot>/arm/state                RobotState       control: INTERACTIVE_HIGH, drop, express
    sudd/<robot>/gripper/state            GripperStatus    control
    sudd/<robot>/policy/chunk             ActionChunk      control
    sudd/<robot>/command/language         LanguageCommand  control
    sudd/<robot>/safety/event             StatusEvent      control
    sudd/<robot>/safety/estop             StatusEvent      estop: REAL_TIME, block, express
    sudd/<robot>/telemetry/<stage>        Telemetry        telemetry: DATA_LOW, drop
    ====================================  ===============  ========================================

Drop semantics: Zenoh's DROP discards what does not fit the transmit queue (after ~1 ms); consumers read
images with `latest()`, a one-slot mailbox that always holds the newest, so the consumer sees drop-oldest.
Control state is also "newest wins"; only the estop blocks (it must arrive, and it is tiny and rare).
Sessions: peer mode, multicast scouting off and loopback-only endpoints by default; peers find each other
only through `listen`/`connect` (gossip over those links lets peers that met a common peer connect directly).
"""

from __future__ import annotations

import json
import logging
import re
import secrets
import socket
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import zenoh

from runtime import messages as m
from sim.config import ConfigError, load_config, spec
from sim.config import validate as check_ranges

log = logging.getLogger(__name__)

ROOT = "sudd"
ARM_STATE, GRIPPER_STATE, POLICY_CHUNK = "arm/state", "gripper/state", "policy/chunk"
LANGUAGE_COMMAND, SAFETY_EVENT, ESTOP = "command/language", "safety/event", "safety/estop"


def camera_color(name: str) -> str:
    return f"camera/{name}/color"


def camera_depth(name: str) -> str:
    return f"camera/{name}/depth"


def telemetry(stage: str) -> str:
    return f"telemetry/{stage}"


@dataclass(frozen=True)
class QoS:
    priority: zenoh.Priority
    congestion: zenoh.CongestionControl
    express: bool  # send at once, no batching: lower latency for small messages
    shm: bool  # publish through shared memory (when the session has it) above SHM_MIN_BYTES


_CTRL = QoS(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, True, False)
QOS = {"image": QoS(zenoh.Priority.DATA, zenoh.CongestionControl.DROP, False, True), "control": _CTRL,
       "estop": QoS(zenoh.Priority.REAL_TIME, zenoh.CongestionControl.BLOCK, True, False),
       "telemetry": QoS(zenoh.Priority.DATA_LOW, zenoh.CongestionControl.DROP, False, False)}
# relative topic pattern -> (message type, QoS class); {x} is one key segment
TOPICS = {"camera/{name}/color": (m.CameraFrame, "image"), "camera/{name}/depth": (m.CameraFrame, "image"),
          ARM_STATE: (m.RobotState, "control"), GRIPPER_STATE: (m.GripperStatus, "control"),
          POLICY_CHUNK: (m.ActionChunk, "control"), LANGUAGE_COMMAND: (m.LanguageCommand, "control"),
          SAFETY_EVENT: (m.StatusEvent, "control"), ESTOP: (m.StatusEvent, "estop"),
          "telemetry/{stage}": (m.Telemetry, "telemetry")}
SHM_MIN_BYTES = 32 * 1024  # below this a copy over the socket is as fast as a shared-memory handle
_SEGMENT = re.compile(r"[A-Za-z0-9_-]{1,64}")
_ENDPOINT = re.compile(r"(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):(\d{1,5})")
_LOOPBACK = re.compile(r"127(\.\d{1,3}){3}|localhost|\[::1\]")


class StaleError(RuntimeError):
    """No message on the topic, or the newest one was received longer ago than the caller accepts."""


def resolve_topic(topic: str, wildcard: bool = False) -> tuple[type[m.Message], QoS]:
    """The message type and QoS of a relative topic; ValueError naming the known topics if it is none."""
    parts = topic.split("/")
    for pattern, (mtype, qos) in TOPICS.items():
        pat = pattern.split("/")
        if len(pat) == len(parts) and all(
                p == s if not p.startswith("{") else (_SEGMENT.fullmatch(s) or (wildcard and s == "*"))
                for p, s in zip(pat, parts)):
            return mtype, QOS[qos]
    raise ValueError(f"unknown topic {topic!r}; known: {', '.join(TOPICS)} (segments: letters, digits, _ -)")


@dataclass(frozen=True)
class BusConfig:
    """Where this process joins the bus. Endpoints are Zenoh locators, e.g. "tcp/127.0.0.1:7447"; a listen
    port of 0 is an ephemeral port picked at open (see `Bus.listen_endpoints`)."""

    robot: str = "ur5"
    mode: str = field(default="peer", metadata=spec(choices=("peer", "client")))
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False  # off: no surprise peers from the LAN, deterministic topology
    loopback_only: bool = True  # refuse non-loopback endpoints unless explicitly allowed
    shm: bool = True  # shared memory between processes on this host (images); falls back to TCP if absent
    shm_pool_mib: int = field(default=32, metadata=spec(1, 4096, "MiB"))
    log_interval_s: float = field(default=5.0, metadata=spec(0.0, 3600.0, "s"))  # decode-error log rate limit

    def __post_init__(self):
        self.validate()

    @classmethod
    def from_dict(cls, data: dict) -> BusConfig:
        return load_config(cls, data)

    def validate(self) -> None:
        check_ranges(self)
        if not _SEGMENT.fullmatch(self.robot):
            raise ConfigError(f"robot = {self.robot!r}: 1-64 letters, digits, _ or -")
        if self.mode == "client" and not self.connect:
            raise ConfigError("mode = 'client' needs at least one connect endpoint (a router)")
        if self.loopback_only and self.multicast_scouting:
            raise ConfigError("multicast_scouting finds peers on the LAN; it needs loopback_only = false")
        for name in ("listen", "connect"):
            for ep in getattr(self, name):
                match = _ENDPOINT.fullmatch(ep) if isinstance(ep, str) else None
                if not match or not (name == "listen" or int(match[3]) > 0) or int(match[3]) > 65535:
                    raise ConfigError(f"{name} endpoint {ep!r} is not <tcp|udp|tls|quic>/<host>:<port>")
                if self.loopback_only and not _LOOPBACK.fullmatch(match[2]):
                    raise ConfigError(f"{name} endpoint {ep!r} is not loopback; set loopback_only = false")


class Received(NamedTuple):
    msg: m.Message
    recv_ns: int  # time.monotonic_ns() at arrival
    key: str

    def age_s(self, now_ns: int | None = None) -> float:
        return ((time.monotonic_ns() if now_ns is None else now_ns) - self.recv_ns) * 1e-9


@dataclass
class SubStats:
    received: int = 0  # decoded, valid messages
    decode_errors: dict[str, int] = field(default_factory=dict)  # reason -> count (never delivered)
    callback_errors: int = 0
    dropped: int = 0  # messages missing from the publishers' seq numbers (lost on the way)
    gaps: int = 0  # how many times seq jumped forward
    out_of_order: int = 0
    duplicates: int = 0
    last_seq: int | None = None


@dataclass
class PubStats:
    published: int = 0
    bytes: int = 0
    shm: int = 0  # puts through shared memory
    shm_fallbacks: int = 0  # shared memory full or failed: sent by copy instead


class Publisher:
    """Publishes one topic's messages, stamping seq, publish time and a random source id into the header."""

    def __init__(self, bus: Bus, topic: str):
        self.topic, self.key = topic, bus.key(topic)
        self.msg_type, self.qos = resolve_topic(topic)
        self.source_id = secrets.randbits(64)
        self.stats = PubStats()
        self._bus, self._seq, self._lock = bus, 0, threading.Lock()
        self._pub = bus.session.declare_publisher(
            self.key, encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(f"sudd/{m.SCHEMA_VERSION}"),
            congestion_control=self.qos.congestion, priority=self.qos.priority, express=self.qos.express)

    def publish(self, msg: m.Message, *, stamp_ns: int | None = None) -> int:
        """Encode and send `msg`; returns its seq. TypeError for the wrong message type, ValueError if invalid."""
        if type(msg) is not self.msg_type:
            raise TypeError(f"{self.topic} carries {self.msg_type.__name__}, not {type(msg).__name__}")
        with self._lock:  # wire order = seq order even with several producer threads; no seq lost on errors
            seq = self._seq + 1
            self._send(msg.encode(seq=seq, stamp_ns=time.monotonic_ns() if stamp_ns is None else stamp_ns,
                                  source_id=self.source_id))
            self._seq = seq
        return seq

    def put_raw(self, data: bytes) -> None:
        """Send bytes as they are, unchecked: for replay tools and fault-injection tests only."""
        with self._lock:
            self._send(data)

    def _send(self, data: bytes) -> None:  # the caller holds self._lock
        provider = self._bus.shm_provider
        payload = data
        if self.qos.shm and provider is not None and len(data) >= SHM_MIN_BYTES:
            try:
                buf = provider.alloc(len(data), policy=zenoh.shm.GarbageCollect())
                buf[0:len(data)] = data
                payload = buf
            except Exception as exc:  # pool exhausted or SHM broken: correctness first, copy it
                self.stats.shm_fallbacks += 1
                log.debug("shm alloc failed on %s (%s); sending by copy", self.key, exc)
        self._pub.put(payload)
        self.stats.published += 1
        self.stats.bytes += len(data)
        self.stats.shm += payload is not data

    def wait_matched(self, timeout_s: float = 5.0) -> bool:
        """Wait until a subscriber for this key is known: declarations take a moment to propagate, and
        what is published before that is lost (there is no history on these topics, by design)."""
        return _wait(lambda: self._pub.matching_status.matching, timeout_s)

    def close(self) -> None:
        self._pub.undeclare()  # only Bus.close calls this: publishers are cached per topic


class Subscription:
    """Decodes every sample; valid ones go to `callback` (on Zenoh's thread: keep it short) and the
    `latest` mailbox, invalid ones are counted per reason and logged at most once per log interval."""

    MAX_SOURCES = 256  # seq trackers kept (bounded: hostile payloads can invent source ids)

    def __init__(self, bus: Bus, topic: str, callback: Callable[[m.Message], None] | None = None):
        self.topic, self.key = topic, bus.key(topic)
        self.msg_type, _ = resolve_topic(topic, wildcard=True)
        self.stats = SubStats()
        self._callback, self._interval = callback, bus.config.log_interval_s
        self._lock = threading.Lock()
        self._latest: Received | None = None
        self._sources: OrderedDict[int, int] = OrderedDict()
        self._last_log: dict[str, tuple[float, int]] = {}
        self._sub = bus.session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        recv_ns = time.monotonic_ns()
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            msg = m.decode(sample.payload.to_bytes())
            if type(msg) is not self.msg_type:
                raise m.DecodeError("wrong_type", f"{type(msg).__name__} on a {self.msg_type.__name__} topic")
        except m.DecodeError as exc:
            self._bad(exc)
            return
        with self._lock:
            self._track(msg)
            self.stats.received += 1
            self._latest = Received(msg, recv_ns, str(sample.key_expr))
        if self._callback is not None:
            try:
                self._callback(msg)
            except Exception:  # a consumer bug must not kill Zenoh's thread or the other consumers
                self.stats.callback_errors += 1
                log.exception("callback on %s failed", self.key)

    def _track(self, msg: m.Message) -> None:
        last = self._sources.get(msg.source_id)
        if last is not None:
            if msg.seq > last + 1:
                self.stats.dropped += msg.seq - last - 1
                self.stats.gaps += 1
            elif msg.seq == last:
                self.stats.duplicates += 1
            elif msg.seq < last:
                self.stats.out_of_order += 1
        self._sources[msg.source_id] = max(msg.seq, last or 0)
        self._sources.move_to_end(msg.source_id)
        if len(self._sources) > self.MAX_SOURCES:
            self._sources.popitem(last=False)
        self.stats.last_seq = msg.seq

    def _bad(self, exc: m.DecodeError) -> None:
        now = time.monotonic()
        with self._lock:
            errors = self.stats.decode_errors
            errors[exc.reason] = errors.get(exc.reason, 0) + 1
            last, count_then = self._last_log.get(exc.reason, (-float("inf"), 0))
            if now - last < self._interval:
                return
            self._last_log[exc.reason] = (now, errors[exc.reason])
        suppressed = errors[exc.reason] - count_then - 1
        log.warning("dropped malformed message on %s: %s%s", self.key, exc,
                    f" ({suppressed} more since the last report)" if suppressed > 0 else "")

    def latest(self, max_age_s: float) -> Received:
        """The newest valid message; StaleError if none yet or it arrived more than `max_age_s` ago."""
        got = self._latest
        if got is None:
            raise StaleError(f"no message received on {self.key} yet")
        age = got.age_s()
        if age > max_age_s:
            raise StaleError(f"newest message on {self.key} is {age * 1e3:.1f} ms old > {max_age_s * 1e3:.1f} ms")
        return got

    def close(self) -> None:
        """Stop receiving (idempotent); the stats and the last message stay readable."""
        with self._lock:
            sub, self._sub = self._sub, None
        if sub is not None:
            sub.undeclare()


class Bus:
    """A Zenoh session with typed publishers and subscriptions: `with Bus.open(cfg) as bus: ...`."""

    def __init__(self, config: BusConfig, session: zenoh.Session, listen: tuple[str, ...]):
        self.config, self.session, self.listen_endpoints = config, session, listen
        self.shm_provider = None
        self._pubs: dict[str, Publisher] = {}
        self._subs: list[Subscription] = []
        self._latest_subs: dict[str, Subscription] = {}
        self._lock = threading.Lock()
        self._closed = False
        if config.shm:
            try:
                self.shm_provider = zenoh.shm.ShmProvider.default_backend(config.shm_pool_mib << 20)
            except Exception as exc:  # no /dev/shm, or a Zenoh build without SHM: frames go by copy
                log.warning("shared memory unavailable (%s); images will be copied over the socket", exc)

    @classmethod
    def open(cls, config: BusConfig | None = None) -> Bus:
        """Open a session. Port-0 listen endpoints get a free port (retried if another process takes it)."""
        config = config or BusConfig()
        for attempt in range(5):
            listen = tuple(_pick_port(ep) for ep in config.listen) if config.mode == "peer" else ()
            try:
                return cls(config, zenoh.open(_zenoh_config(config, listen)), listen)
            except zenoh.ZError as exc:
                if attempt == 4 or not any(ep.endswith(":0") for ep in config.listen):
                    raise
                log.debug("zenoh open failed (%s); retrying with other ports", exc)
        raise AssertionError("unreachable")

    def key(self, topic: str) -> str:
        return f"{ROOT}/{self.config.robot}/{topic}"

    def publisher(self, topic: str) -> Publisher:
        """The (cached) publisher of `topic`, with the topic's QoS."""
        with self._lock:
            self._check_open()
            if topic not in self._pubs:
                self._pubs[topic] = Publisher(self, topic)
            return self._pubs[topic]

    def subscribe(self, topic: str, callback: Callable[[m.Message], None] | None = None) -> Subscription:
        """Subscribe to `topic` (a `*` segment matches any camera/stage name)."""
        with self._lock:
            self._check_open()
            sub = Subscription(self, topic, callback)
            self._subs.append(sub)
            self._latest_subs.setdefault(topic, sub)
            return sub

    def latest(self, topic: str, max_age_s: float) -> Received:
        """Newest message on `topic` no older than `max_age_s` (StaleError otherwise). The first call on a
        topic without a subscription subscribes and raises StaleError: subscribe at start-up instead."""
        sub = self._latest_subs.get(topic) or self.subscribe(topic)
        return sub.latest(max_age_s)

    def wait_for_peers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        """Wait until `n` peers or routers are connected (a connect to a peer not up yet retries meanwhile)."""
        info = self.session.info
        return _wait(lambda: len(info.peers_zid()) + len(info.routers_zid()) >= n, timeout_s)

    def stats(self) -> dict:
        """Per-topic counters: {"pub": {topic: PubStats}, "sub": {topic: [SubStats, ...]}}."""
        subs: dict[str, list] = {}
        for s in self._subs:
            subs.setdefault(s.topic, []).append(s.stats)
        return {"pub": {t: p.stats for t, p in self._pubs.items()}, "sub": subs}

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("bus is closed")

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for s in self._subs:
                s.close()
            for p in self._pubs.values():
                p.close()
        self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _wait(cond: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def _pick_port(endpoint: str) -> str:
    """Replace port 0 with a free one: Zenoh's Python API does not report the port it bound."""
    proto, rest = endpoint.split("/", 1)
    host, port = rest.rsplit(":", 1)
    if port != "0":
        return endpoint
    family = socket.AF_INET6 if host.startswith("[") else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM) as s:
        s.bind((host.strip("[]"), 0))
        return f"{proto}/{host}:{s.getsockname()[1]}"


def _zenoh_config(cfg: BusConfig, listen: tuple[str, ...]) -> zenoh.Config:
    zc = zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    zc.insert_json5("listen/endpoints", json.dumps(list(listen)))
    zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    zc.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shm))
    return zc
