"""FakeRobotiqServer: a loopback TCP server speaking the Robotiq URCap socket protocol over a simulated 2F-85.

Why: the real driver (`runtime/drivers/robotiq.py`) is tested against the protocol as the URCap speaks it,
without a robot: `SET VAR v ...` answered by `ack` (no newline), `GET VAR` by `VAR v\\n`. The simulated
gripper is lazy (state advanced from the wall clock on each request), so it needs no thread of its own:

* activation: ACT 1 from reset -> STA 1 for `activation_s`, then STA 3; ACT 0 resets (STA 0, GTO 0).
* motion: with STA 3 and GTO 1 the fingers move toward the request at the speed register's rate (the real
  2F-85's 20-150 mm/s over its 85 mm stroke, times `speed_scale`), OBJ 0 while moving, 3 on arrival.
* PRE echoes a new POS request `echo_delay_s` later (until then OBJ still describes the previous move).
* `place_object(register)`: an object the fingers stop on at that register: closing onto it -> OBJ 2; with
  `outer=True` the fingers stop on it while opening -> OBJ 1.
* faults for tests: `reply_hook(line) -> bytes | None` replaces the reply (None: stay silent),
  `drop_connections()` closes every client socket, `activation_hangs` keeps STA at 1.
"""

from __future__ import annotations

import socket
import threading
import time

STROKE_MM = 85.0
SPEED_MM_S = (20.0, 150.0)
_WRITABLE = {"ACT", "GTO", "ATR", "ARD", "FOR", "SPE", "POS"}
_READABLE = _WRITABLE | {"STA", "PRE", "OBJ", "FLT"}


class FakeRobotiqServer:
    def __init__(self, host: str = "127.0.0.1", port: int = 0, speed_scale: float = 1.0,
                 activation_s: float = 0.2, echo_delay_s: float = 0.008, closed_limit: int = 255):
        self.speed_scale, self.activation_s, self.echo_delay_s = speed_scale, activation_s, echo_delay_s
        self.closed_limit = closed_limit  # the finger register where the fingers touch each other
        self.lock = threading.RLock()
        self.regs = {"ACT": 0, "GTO": 0, "ATR": 0, "ARD": 0, "FOR": 0, "SPE": 0, "POS": 0,
                     "STA": 0, "PRE": 0, "OBJ": 0, "FLT": 0}
        self.position = 0.0  # measured finger register (float while moving)
        self.object: tuple[int, bool] | None = None  # (register, outer)
        self.reply_hook = None
        self.activation_hangs = False
        self.requests: list[str] = []
        self._pending: tuple[float, int] | None = None  # (echo time, requested register)
        self._active_at: float | None = None
        self._last = time.monotonic()
        self._listener = socket.create_server((host, port))
        self.address = self._listener.getsockname()[:2]
        self._clients: list[socket.socket] = []
        self._running = True
        self._thread = threading.Thread(target=self._accept, name="fake-robotiq", daemon=True)
        self._thread.start()

    # -- test controls ---------------------------------------------------------------------------------------
    def place_object(self, register: int | None, outer: bool = False) -> None:
        with self.lock:
            self._advance()
            self.object = None if register is None else (int(register), outer)

    def drop_connections(self) -> None:
        with self.lock:
            for c in self._clients:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self._clients.clear()

    def close(self) -> None:
        self._running = False
        self._listener.close()
        self.drop_connections()
        self._thread.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- simulation ------------------------------------------------------------------------------------------
    def _advance(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        r = self.regs
        if r["STA"] == 1 and self._active_at is not None and now >= self._active_at and not self.activation_hangs:
            r["STA"], self._active_at = 3, None
        if r["STA"] != 3:
            return
        if self._pending is not None and now >= self._pending[0]:
            r["PRE"], self._pending = self._pending[1], None
            r["OBJ"] = 0 if r["GTO"] else r["OBJ"]
        if not r["GTO"] or self._pending is not None or r["OBJ"] != 0:
            return
        target = min(r["PRE"], self.closed_limit)
        mm_s = SPEED_MM_S[0] + (SPEED_MM_S[1] - SPEED_MM_S[0]) * r["SPE"] / 255
        step = mm_s / STROKE_MM * 255 * self.speed_scale * dt
        new = self.position + max(-step, min(step, target - self.position))
        if self.object is not None:
            obj, outer = self.object
            if not outer and self.position <= obj <= new:  # closing onto the object
                self.position, r["OBJ"] = float(obj), 2
                return
            if outer and new <= obj <= self.position:  # opening against it
                self.position, r["OBJ"] = float(obj), 1
                return
        self.position = new
        if abs(new - target) < 1e-9:
            r["OBJ"] = 3

    def handle(self, line: str) -> bytes | None:
        """The reply to one request line (reply hooks may call this to pass a request through)."""
        parts = line.split()
        with self.lock:
            self._advance()
            r = self.regs
            if len(parts) == 2 and parts[0] == "GET" and parts[1] in _READABLE:
                value = round(self.position) if parts[1] == "POS" else r[parts[1]]
                return f"{parts[1]} {value}\n".encode()
            if len(parts) >= 3 and len(parts) % 2 == 1 and parts[0] == "SET":
                pairs = list(zip(parts[1::2], parts[2::2]))
                if all(k in _WRITABLE and v.isdigit() and int(v) <= 255 for k, v in pairs):
                    for k, v in pairs:
                        self._set(k, int(v))
                    return b"ack"
            return b"?"  # what the real URCap answers to nonsense is not documented; the driver never sends it

    def _set(self, var: str, value: int) -> None:
        r = self.regs
        if var == "ACT":
            if value == 0:
                r.update(ACT=0, GTO=0, STA=0, OBJ=0, FLT=0)
                self._pending = self._active_at = None
            elif r["STA"] == 0:
                r.update(ACT=1, STA=1)
                self._active_at = time.monotonic() + self.activation_s
            return
        r[var] = value
        if var == "POS" and r["STA"] == 3:
            self._pending = (time.monotonic() + self.echo_delay_s, value)
        if var == "GTO" and value == 1 and r["STA"] == 3 and self._pending is None and r["PRE"] != round(self.position):
            r["OBJ"] = 0  # go again toward the standing request

    # -- sockets ---------------------------------------------------------------------------------------------
    def _accept(self) -> None:
        self._listener.settimeout(0.05)  # closing a listener does not wake accept() on every platform
        while self._running:
            try:
                conn, _ = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.settimeout(None)
            with self.lock:
                self._clients.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        try:
            while True:
                data = conn.recv(1024)
                if not data:
                    return
                buf += data
                while b"\n" in buf:
                    raw, buf = buf.split(b"\n", 1)
                    line = raw.decode("ascii", "replace").strip()
                    self.requests.append(line)
                    reply = self.reply_hook(line) if self.reply_hook is not None else self.handle(line)
                    if reply is not None:
                        conn.sendall(reply)
        except OSError:
            return
        finally:
            conn.close()
