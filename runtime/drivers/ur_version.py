"""Which UR generation answers at an address: a raw RTDE handshake (protocol 2, GET_URCONTROL_VERSION) with a
timeout, before ur_rtde connects. Why: ur_rtde's connect has no timeout and hangs on an unreachable robot, and the
controller version decides the stream rate (e-Series 500 Hz, CB3 125 Hz).
"""

from __future__ import annotations

import socket
import struct


def frequency_for_version(major: int) -> float:
    """ur_rtde's rule: a controller major version above CB3's 3 (PolyScope 5, X 10) streams at 500 Hz."""
    return 500.0 if major > 3 else 125.0


def query_controller_version(host: str, timeout: float, port: int = 30004) -> tuple[int, int, int, int]:
    """(major, minor, bugfix, build) over a short RTDE session: REQUEST_PROTOCOL_VERSION 2, GET_URCONTROL_VERSION."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock, sock.makefile("rb") as f:

            def reply(want: int) -> bytes:
                while True:  # skips anything else (text messages)
                    head = f.read(3)
                    size, cmd = struct.unpack(">HB", head) if len(head) == 3 else (3, None)
                    body = f.read(size - 3)
                    if cmd is None or len(body) < size - 3:
                        raise ConnectionResetError("the controller closed the connection")
                    if cmd == want:
                        return body

            sock.sendall(struct.pack(">HBH", 5, ord("V"), 2))
            if reply(ord("V"))[:1] != b"\x01":
                raise ConnectionError(f"the controller at {host}:{port} refused RTDE protocol version 2")
            sock.sendall(struct.pack(">HB", 3, ord("v")))
            return struct.unpack(">IIII", reply(ord("v"))[:16])
    except OSError as exc:
        raise ConnectionError(f"no UR controller answers RTDE at {host}:{port} ({exc}); is the robot on and "
                              "the address right?") from exc


__all__ = ["frequency_for_version", "query_controller_version"]
