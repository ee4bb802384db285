"""Where a process joins the bus: `BusConfig`, validated on creation, and the Zenoh session config it gives.

Sessions: peer mode, multicast scouting off and loopback-only endpoints by default; peers find each other
only through `listen`/`connect` (gossip over those links lets peers that met a common peer connect directly).
"""

from __future__ import annotations

import json
import re
import socket
from dataclasses import dataclass, field

import zenoh

from runtime.bus_topics import SEGMENT
from sim.config import ConfigError, load_config, spec
from sim.config import validate as check_ranges

_ENDPOINT = re.compile(r"(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):(\d{1,5})")
_LOOPBACK = re.compile(r"127(\.\d{1,3}){3}|localhost|\[::1\]")


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
        if not SEGMENT.fullmatch(self.robot):
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


def is_loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (`tcp/127.0.0.1:7447`) names this host's loopback interface."""
    match = _ENDPOINT.fullmatch(endpoint)
    return bool(match and _LOOPBACK.fullmatch(match[2]))


def split_endpoint(endpoint: str) -> tuple[str, str, str]:
    """`tcp/127.0.0.1:7447` -> ("tcp", "127.0.0.1", "7447")."""
    proto, rest = endpoint.split("/", 1)
    host, port = rest.rsplit(":", 1)
    return proto, host, port


def pick_port(endpoint: str) -> str:
    """Replace port 0 with a free one: Zenoh's Python API does not report the port it bound."""
    proto, host, port = split_endpoint(endpoint)
    if port != "0":
        return endpoint
    family = socket.AF_INET6 if host.startswith("[") else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM) as s:
        s.bind((host.strip("[]"), 0))
        return f"{proto}/{host}:{s.getsockname()[1]}"


def zenoh_config(cfg: BusConfig, listen: tuple[str, ...]) -> zenoh.Config:
    """The Zenoh session config of `cfg`, listening on `listen` (its endpoints with port 0 already picked)."""
    zc = zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    zc.insert_json5("listen/endpoints", json.dumps(list(listen)))
    zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    zc.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shm))
    return zc
