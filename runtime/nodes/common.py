"""What every runtime node shares: bus settings, the process entry, stop handling and the ready signal.

A node is a function `run(cfg, ctx) -> dict` in its own process. `ctx` (NodeContext) carries the stop
request (a multiprocessing Event from the launcher, or a threading Event when run in-process), the ready
callback and the parent-liveness check. The function must:

* open its bus, subscribe, start its devices, then call `ctx.ready(info)` (the launcher waits for it);
* loop on the monotonic clock until `ctx.should_stop()` (stop requested, or the launcher died);
* leave its hardware safe in a `finally` (the robot node: a controlled stop through the safety filter);
* return a JSON-able report (counters, latencies), which the launcher collects.

Signals: a node process ignores SIGINT (Ctrl-C reaches the whole process group, but only the launcher may
decide the order of the shutdown: robot first) and turns SIGTERM into a stop request.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

HUB_DEFAULT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class BusSettings:
    """Where a node joins the bus: its own ephemeral listen port, connected to the launcher's hub."""

    robot: str = "ur5"
    connect: tuple[str, ...] = (HUB_DEFAULT,)
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    shm: bool = True
    loopback_only: bool = True  # the launcher clears it when its hub is on a network address

    def open(self, wait_peers_s: float = 5.0):
        from runtime.bus import Bus, BusConfig

        bus = Bus.open(BusConfig(robot=self.robot, listen=self.listen, connect=self.connect, shm=self.shm,
                                 loopback_only=self.loopback_only))
        if self.connect:
            bus.wait_for_peers(1, wait_peers_s)
        return bus


class NodeContext:
    """Stop request, ready signal and parent watch of one node (see the module docstring)."""

    def __init__(self, name: str, stop_event=None, ready_cb=None, watch_parent: bool = False, winding_event=None):
        self.name = name
        self.stop_event = stop_event if stop_event is not None else threading.Event()
        self.winding_event = winding_event  # the launcher's shutdown has begun (winding_down)
        self._ready_cb = ready_cb
        self._watch_parent = watch_parent
        self._parent_pid = os.getppid()
        self.ready_info: dict | None = None
        self.stop_reason: str | None = None

    def ready(self, info: dict | None = None) -> None:
        self.ready_info = dict(info or {})
        if self._ready_cb is not None:
            self._ready_cb(self.ready_info)

    def request_stop(self, reason: str = "requested") -> None:
        self.stop_reason = self.stop_reason or reason
        self.stop_event.set()

    def should_stop(self) -> bool:
        if self.stop_event.is_set():
            self.stop_reason = self.stop_reason or "stop requested"
            return True
        if self._watch_parent and os.getppid() != self._parent_pid:  # the launcher died: re-parented
            self.request_stop("launcher died")
            return True
        return False

    def winding_down(self) -> bool:
        """The stack is stopping: this node's stop, or the launcher's shutdown begun (the robot node stops first, so
        its state and frames end while the other nodes still run; that is no fault to warn of)."""
        return self.should_stop() or (self.winding_event is not None and self.winding_event.is_set())

    def sleep_until(self, t_mono: float) -> bool:
        """Sleep until time.monotonic() >= t_mono or a stop; True if stopping."""
        dt = t_mono - time.monotonic()
        if dt > 0:
            self.stop_event.wait(dt)
        return self.should_stop()


def config_to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def config_from_dict(cls, d: dict):
    """Rebuild a (possibly nested) config dataclass from `config_to_dict` output; lists become tuples."""
    kw = {}
    hints = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        if k not in hints:
            raise ValueError(f"{cls.__name__} has no field {k!r}")
        f = hints[k]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(sub) and isinstance(v, dict):
            v = config_from_dict(type(sub), v)
        elif isinstance(v, list):
            v = tuple(v)
        kw[k] = v
    return cls(**kw)


def percentiles(xs, scale: float = 1.0) -> dict:
    """p50/p99/max/n of a sample (multiplied by `scale`); empty dict for no samples."""
    a = np.asarray(list(xs), dtype=float) * scale
    a = a[np.isfinite(a)]
    if not a.size:
        return {"n": 0}
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max()),
            "n": int(a.size)}


def process_entry(module: str, cfg_dict: dict, name: str, status_q, stop_event, winding_event=None) -> None:
    """multiprocessing (spawn) target: run `module.run(cfg, ctx)`, reporting ready/exit on `status_q`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stop_event.set())
    logging.basicConfig(level=os.environ.get("SUDD_LOG", "WARNING"),
                        format=f"%(asctime)s {name} %(levelname)s %(name)s: %(message)s")
    mod = importlib.import_module(module)
    cfg = config_from_dict(mod.CONFIG, cfg_dict)
    ctx = NodeContext(name, stop_event, lambda info: status_q.put((name, "ready", info)), watch_parent=True,
                      winding_event=winding_event)
    report: dict = {"ok": False}
    try:
        report = mod.run(cfg, ctx) or {}
        report.setdefault("ok", True)
    except BaseException as exc:  # reported, then the process exits non-zero: the launcher sees a crash
        log.exception("node %s failed", name)
        report = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        status_q.put((name, "exit", report))
        status_q.close()
        status_q.join_thread()
        raise SystemExit(1) from None
    status_q.put((name, "exit", report))
    status_q.close()
    status_q.join_thread()


def cli_main(module: str, argv: list[str] | None = None) -> int:
    """`python -m runtime.nodes.X --config '{...json...}'`: run one node in the foreground (Ctrl-C stops it)."""
    import argparse

    p = argparse.ArgumentParser(prog=f"python -m {module}")
    p.add_argument("--config", default="{}", help="the node's config as JSON (fields of its config dataclass)")
    args = p.parse_args(argv)
    mod = importlib.import_module(module)
    cfg = config_from_dict(mod.CONFIG, json.loads(args.config))
    ctx = NodeContext(module.rsplit(".", 1)[-1], ready_cb=lambda info: print(json.dumps({"ready": info}), flush=True))
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: ctx.request_stop("signal"))
    report = mod.run(cfg, ctx)
    print(json.dumps({"report": report}, default=str), flush=True)
    return 0 if report.get("ok", True) else 1


__all__ = ["BusSettings", "NodeContext", "HUB_DEFAULT", "process_entry", "cli_main", "percentiles",
           "config_to_dict", "config_from_dict"]
