"""Robotiq2F85: the Robotiq 2F-85 as a `GripperDriver`, over the Robotiq URCap's socket on the UR controller.

The URCap runs a TCP server (port 63352) that speaks ASCII lines to the gripper's registers:
`SET ACT 1 GTO 1 ...\\n` (several VAR value pairs per line) is answered by the three bytes `ack` (no newline);
`GET VAR\\n` by `VAR value\\n` (or `VAR ?` while the gripper cannot be read, e.g. during an emergency stop).
Registers: ACT activate, GTO go-to, ATR auto-release, POS/SPE/FOR requested position/speed/force (0..255),
STA activation status (0 reset, 1 activating, 3 active), PRE echo of the requested position, OBJ object
detection (0 moving, 1 stopped on an object while opening, 2 while closing, 3 at the requested position),
FLT fault code, POS (on GET) the measured finger position.

Why the details: the gripper echoes a new request in PRE a cycle later, and until then OBJ still describes the
previous move, so `move(wait=True)` waits for PRE == requested before polling OBJ (as ur_rtde does). Position
0..1 maps onto the calibrated register bounds (`open_register`/`closed_register`: a 2F-85 closed on nothing
reads ~225-230, not 255), so 0 and 1 mean measured fully open/closed like the twin. Every request has a
deadline (no call can hang); after a timeout, a malformed reply or a dropped link the socket is closed (a
late reply must not be read as the answer to the next request) and the next call reconnects.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

from sim.devices import GripperState, check_scalar

_ACTIVE = 3
_MOVING = 0
_QUIET_S = 0.02  # a GET reply without a newline counts as complete after this long with no more bytes


class RobotiqProtocolError(ConnectionError):
    """The URCap answered something that is not the protocol (the connection is closed and reopened)."""


class GripperStateError(RuntimeError):
    """The gripper cannot report a register in its current state (URCap answers `?`, e.g. emergency stop)."""


@dataclass(frozen=True)
class RobotiqConfig:
    host: str
    port: int = 63352
    timeout: float = 2.0  # s, connect and each request/reply
    open_register: int = 0  # POS reading when fully open (calibrate per gripper)
    closed_register: int = 255  # POS reading when fully closed on nothing (2F-85: ~225-230)
    move_timeout_s: float = 5.0  # wait=True: the fingers must stop within this
    activation_timeout_s: float = 10.0
    poll_s: float = 0.01  # status polling period while waiting

    def __post_init__(self):
        check_scalar("port", self.port, 1, 65535)
        check_scalar("timeout", self.timeout, 0.01, 60.0, "s")
        check_scalar("open_register", self.open_register, 0, 254)
        check_scalar("closed_register", self.closed_register, self.open_register + 1, 255)
        check_scalar("move_timeout_s", self.move_timeout_s, 0.01, 600.0, "s")
        check_scalar("activation_timeout_s", self.activation_timeout_s, 0.01, 600.0, "s")
        check_scalar("poll_s", self.poll_s, 0.0, 1.0, "s")


class Robotiq2F85:
    """GripperDriver for a 2F-85 behind the URCap socket. Connects lazily; `activate()` before moving."""

    def __init__(self, config: RobotiqConfig):
        self.config = config
        self._addr = f"{config.host}:{config.port}"
        self._sock: socket.socket | None = None
        self._lock = threading.RLock()
        self._activated = False
        self._target: float | None = None

    # -- GripperDriver ---------------------------------------------------------------------------------------
    def activate(self) -> None:
        """Reset (ACT 0) then activate (ACT 1) and wait for STA 3. A gripper already active without a fault
        is left alone: activation runs a full open/close stroke, which would drop a held object."""
        deadline = time.monotonic() + self.config.activation_timeout_s
        if self.get("STA") == _ACTIVE and self.get("FLT") == 0:
            self._activated = True
            return
        self._activated = False
        self.set(ACT=0, ATR=0)
        self._wait(lambda: self.get("ACT") == 0 and self.get("STA") == 0, deadline, "reset (ACT 0)")
        self.set(ACT=1)
        self._wait(lambda: self.get("STA") == _ACTIVE, deadline, "activation (ACT 1)")
        self._activated = True

    def move(self, position: float, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        position = check_scalar("position", position, 0.0, 1.0)
        speed = check_scalar("speed", speed, 0.0, 1.0)
        force = check_scalar("force", force, 0.0, 1.0)
        if not self._activated:
            return False
        if self.get("STA") != _ACTIVE:  # reset behind our back (pendant, fault, power cycle)
            self._activated = False
            return False
        reg = self._to_register(position)
        self.set(POS=reg, SPE=round(speed * 255), FOR=round(force * 255), GTO=1)
        self._target = position
        if wait:
            deadline = time.monotonic() + self.config.move_timeout_s
            # Until PRE echoes the request, OBJ still describes the previous move.
            self._wait(lambda: self.get("PRE") == reg, deadline, f"request POS {reg} to be echoed in PRE")
            self._wait(lambda: self.get("OBJ") != _MOVING, deadline, f"fingers to stop (POS {reg})")
        return True

    def open(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        return self.move(0.0, speed, force, wait)

    def close(self, speed: float = 0.5, force: float = 0.5, wait: bool = True) -> bool:
        return self.move(1.0, speed, force, wait)

    def state(self) -> GripperState:
        with self._lock:  # one consistent snapshot, even with other threads polling
            pos = self.get("POS")
            stamp = time.monotonic_ns()
            sta, gto, obj = self.get("STA"), self.get("GTO"), self.get("OBJ")
            target = self._target if self._target is not None else self._from_register(self.get("PRE"))
        return GripperState(position=self._from_register(pos), target=target,
                            is_moving=sta == _ACTIVE and gto == 1 and obj == _MOVING,
                            object_detected=sta == _ACTIVE and obj in (1, 2), timestamp_ns=stamp,
                            is_activated=sta == _ACTIVE)

    def disconnect(self) -> None:
        with self._lock:
            self._drop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.disconnect()

    # -- protocol --------------------------------------------------------------------------------------------
    def get(self, var: str) -> int:
        """`GET VAR` -> its integer value."""
        line = self._request(f"GET {var}", var)
        parts = line.split()
        if len(parts) != 2 or parts[0] != var:
            self._fail(RobotiqProtocolError(f"Robotiq at {self._addr}: unexpected reply {line!r} to 'GET {var}'"))
        if parts[1].startswith("?"):
            raise GripperStateError(f"Robotiq at {self._addr} cannot report {var} now (reply {line!r}); "
                                    "is an emergency stop active?")
        try:
            return int(parts[1])
        except ValueError:
            self._fail(RobotiqProtocolError(f"Robotiq at {self._addr}: non-integer reply {line!r} to 'GET {var}'"))

    def set(self, **values: int) -> None:
        """`SET VAR value ...` (one line, applied together); raises unless the URCap answers `ack`."""
        for var, v in values.items():
            if not isinstance(v, int) or not 0 <= v <= 255:
                raise ValueError(f"{var} = {v!r} is out of range; allowed: [0, 255]")
        cmd = "SET " + " ".join(f"{var} {v}" for var, v in values.items())
        reply = self._request(cmd, None)
        if reply != "ack":
            self._fail(RobotiqProtocolError(f"Robotiq at {self._addr}: expected 'ack' to {cmd!r}, got {reply!r}"))

    def _request(self, cmd: str, var: str | None) -> str:
        with self._lock:
            sock = self._connected()
            try:
                self._drain(sock)
                sock.sendall(cmd.encode("ascii") + b"\n")
                return self._reply(sock, cmd, var)
            except socket.timeout:
                self._fail(TimeoutError(f"Robotiq at {self._addr}: no reply to {cmd!r} within "
                                        f"{self.config.timeout} s"))
            except OSError as exc:
                self._fail(ConnectionError(f"Robotiq at {self._addr}: connection lost during {cmd!r} ({exc}); "
                                           "it is reopened on the next call"), exc)

    def _reply(self, sock: socket.socket, cmd: str, var: str | None) -> str:
        """The first reply line. `ack` ends without a newline, and a reply that stops arriving for _QUIET_S
        is taken as complete, so a server that omits newlines is served and a malformed one is reported."""
        deadline = time.monotonic() + self.config.timeout
        buf = b""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise socket.timeout()
            sock.settimeout(min(remaining, _QUIET_S) if buf.strip() else remaining)
            try:
                chunk = sock.recv(1024)
            except socket.timeout:
                if buf.strip():
                    return buf.strip().decode("ascii", "replace")
                raise
            if not chunk:
                raise ConnectionResetError("the server closed the connection")
            buf += chunk
            text = buf.lstrip()
            if b"\n" in text:
                return text.split(b"\n", 1)[0].decode("ascii", "replace").strip()
            if var is None and len(text.strip()) >= 3:
                return text.strip().decode("ascii", "replace")

    def _connected(self) -> socket.socket:
        if self._sock is None:
            try:
                sock = socket.create_connection((self.config.host, self.config.port), timeout=self.config.timeout)
            except OSError as exc:
                raise ConnectionError(f"cannot connect to the Robotiq URCap server at {self._addr} ({exc}); is "
                                      "the robot on and the Robotiq URCap installed?") from exc
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._sock = sock
        return self._sock

    def _drain(self, sock: socket.socket) -> None:
        """Discard bytes left from the previous reply (e.g. a newline after `ack`); notice a closed peer."""
        sock.setblocking(False)
        try:
            while True:
                data = sock.recv(1024)
                if not data:
                    raise ConnectionResetError("the server closed the connection")
        except BlockingIOError:
            pass
        finally:
            if self._sock is sock:
                sock.settimeout(self.config.timeout)

    def _drop(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def _fail(self, exc: Exception, cause: BaseException | None = None):
        self._drop()
        raise exc from cause

    def _wait(self, done, deadline: float, what: str) -> None:
        while not done():
            if time.monotonic() > deadline:
                sta, flt = self.get("STA"), self.get("FLT")
                raise TimeoutError(f"Robotiq at {self._addr}: timed out waiting for {what} (STA={sta}, FLT={flt}); "
                                   "check the gripper's power and cable and clear faults on the pendant")
            time.sleep(self.config.poll_s)

    # -- units -----------------------------------------------------------------------------------------------
    def _to_register(self, position: float) -> int:
        lo, hi = self.config.open_register, self.config.closed_register
        return int(round(lo + position * (hi - lo)))

    def _from_register(self, reg: int) -> float:
        lo, hi = self.config.open_register, self.config.closed_register
        return min(1.0, max(0.0, (reg - lo) / (hi - lo)))
