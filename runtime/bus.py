"""The runtime bus: typed `runtime.messages` over Zenoh 1.x, with per-topic QoS and counted bad input.

Why Zenoh: one peer-to-peer pub/sub that is ~75 us a hop on loopback, carries camera frames through shared
memory, and is what rmw_zenoh (ROS 2) speaks, so a ROS tool can join later without a bridge. Why a wrapper:
every topic has one message type and one QoS, decided once (an estop is never dropped, an old frame always
is), every payload is decoded and validated once at the edge, and bad payloads are counted per reason
instead of reaching the policy or the arm.

This module is the session wrapper: `Bus`, its cached `Publisher`s and its `Subscription`s. The key layout,
topic names and QoS classes are in `runtime.bus_topics`; where a process joins (`BusConfig`, endpoints,
the Zenoh config) is in `runtime.bus_config`. Both are re-exported here, so `from runtime.bus import ...`
reaches all of it.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import zenoh

from runtime import messages as m
from runtime.bus_config import BusConfig, pick_port, zenoh_config
from runtime.bus_topics import (  # noqa: F401 - the topic names and QoS table are part of this module's API
    ARM_STATE,
    ESTOP,
    GRIPPER_STATE,
    LANGUAGE_COMMAND,
    POLICY_CHUNK,
    QOS,
    ROOT,
    SAFETY_EVENT,
    SHM_MIN_BYTES,
    TOPICS,
    QoS,
    camera_color,
    camera_depth,
    resolve_topic,
    telemetry,
)

log = logging.getLogger(__name__)
_pick_port = pick_port  # the name runtime.launch imports


class StaleError(RuntimeError):
    """No message on the topic, or the newest one was received longer ago than the caller accepts."""


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
            listen = tuple(pick_port(ep) for ep in config.listen) if config.mode == "peer" else ()
            try:
                return cls(config, zenoh.open(zenoh_config(config, listen)), listen)
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
