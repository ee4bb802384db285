"""The RTDE wire protocol (port 30004) as the fake UR controller serves it: framing, field types, one session.

Source of truth: Universal Robots' RTDE guide (protocol version 2) and what ur_rtde 1.6's `rtde.cpp` sends and
parses. Every message is `uint16 size (header included), uint8 type, payload`, big-endian:

* 'V' REQUEST_PROTOCOL_VERSION: uint16 version -> uint8 accepted (1 for versions 1 and 2).
* 'v' GET_URCONTROL_VERSION: -> uint32 major, minor, bugfix, build (ur_rtde picks 500 Hz for major > 3).
* 'O' SETUP_OUTPUTS: double frequency + comma-separated names (ur_rtde leaves a trailing comma) ->
  uint8 recipe id + comma-separated types; an unknown name answers NOT_FOUND in its place (recipe id 0, the
  recipe is not kept) and ur_rtde then throws "The following variables was not found by the controller".
* 'I' SETUP_INPUTS: names -> uint8 recipe id (1, 2, ... per connection) + types; NOT_FOUND for unknown names,
  IN_USE for an input another connection owns (the controller lets one client write a field).
* 'S' START / 'P' PAUSE -> uint8 accepted; after START the controller streams 'U' data packages
  (uint8 output recipe id + the fields packed in recipe order) at the requested frequency.
* 'U' from the client: uint8 input recipe id + the recipe's fields -> written to the input registers.
* 'M' text messages from the client are accepted and ignored.
"""

from __future__ import annotations

import re
import socket
import struct
import threading
import time

HEADER = struct.Struct(">HB")
VERSION, CONTROL_VERSION, TEXT, DATA, SETUP_OUTPUTS, SETUP_INPUTS, START, PAUSE = (
    ord("V"), ord("v"), ord("M"), ord("U"), ord("O"), ord("I"), ord("S"), ord("P"))

CODES = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
         "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}
_SIZES = {"BOOL": 1, "UINT8": 1, "UINT32": 1, "UINT64": 1, "INT32": 1, "DOUBLE": 1,
          "VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}

# Output fields of the RTDE guide (names and types; registers are matched by pattern below).
_V6D = ("target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
        "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed "
        "joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia").split()
_DOUBLE = ("timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
           "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
           "standard_analog_output0 standard_analog_output1 tool_analog_input0 tool_analog_input1 "
           "tool_output_current tool_temperature payload speed_slider_fraction").split()
OUTPUT_TYPES = {**{n: "VECTOR6D" for n in _V6D}, **{n: "DOUBLE" for n in _DOUBLE},
                "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
                "robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32", "tool_mode": "UINT32",
                "joint_mode": "VECTOR6INT32", "runtime_state": "UINT32", "robot_status_bits": "UINT32",
                "safety_status_bits": "UINT32", "actual_tool_accelerometer": "VECTOR3D", "payload_cog": "VECTOR3D",
                "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "tool_output_voltage": "INT32",
                "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
                "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
                "speed_slider_mask": "UINT32"}
INPUT_TYPES = {"speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE", "external_force_torque": "VECTOR6D",
               "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
               "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
               "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
               "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
               "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
               "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32"}
_REGISTER = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)$")
_REG_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}


def _register_type(name: str, want: tuple[str, ...]) -> str | None:
    m = _REGISTER.match(name)
    if not m or m.group(1) not in want:
        return None
    kind, idx = m.group(2), int(m.group(3))
    limit = 128 if kind == "bit" else 48  # bit registers 64..127, int/double registers 0..47
    lo = 64 if kind == "bit" else 0
    return _REG_TYPES[kind] if lo <= idx < limit else None


def output_type(name: str) -> str | None:
    """The RTDE type of an output field (readable registers include the input registers), None if unknown."""
    return OUTPUT_TYPES.get(name) or _register_type(name, ("input", "output"))


def input_type(name: str) -> str | None:
    return INPUT_TYPES.get(name) or _register_type(name, ("input",))


def default_value(rtde_type: str):
    n = _SIZES[rtde_type]
    zero = 0.0 if rtde_type in ("DOUBLE", "VECTOR3D", "VECTOR6D") else 0
    return zero if n == 1 else (zero,) * n


def struct_format(types: list[str]) -> struct.Struct:
    return struct.Struct(">B" + "".join(CODES[t] for t in types))


def send_message(sock: socket.socket, cmd: int, payload: bytes = b"") -> None:
    sock.sendall(HEADER.pack(HEADER.size + len(payload), cmd) + payload)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionResetError("the RTDE client closed the connection")
        buf += chunk
    return buf


def read_message(sock: socket.socket) -> tuple[int, bytes]:
    size, cmd = HEADER.unpack(_recv_exact(sock, HEADER.size))
    return cmd, _recv_exact(sock, size - HEADER.size)


class RtdeSession:
    """One client connection: its recipes, frequency and start state. `controller` provides `version`,
    `max_frequency`, `claim_input(session, name)`, `write_inputs(names, values)`, `log(event, detail)`."""

    def __init__(self, sock: socket.socket, controller):
        self.sock, self.controller = sock, controller
        self.send_lock = threading.Lock()
        self.protocol = 1
        self.outputs: tuple[list[str], list[str], struct.Struct] | None = None
        self.frequency = 0.0
        self.inputs: list[tuple[list[str], list[str], struct.Struct]] = []
        self.started = False
        self.next_due = 0.0
        self.closed = False

    def serve(self) -> None:
        """Answer requests until the client leaves (runs in the connection's thread)."""
        try:
            while True:
                cmd, payload = read_message(self.sock)
                self.handle(cmd, payload)
        except (OSError, struct.error, IndexError):
            pass
        finally:
            self.close()

    def handle(self, cmd: int, payload: bytes) -> None:
        c = self.controller
        if cmd == VERSION:
            version = struct.unpack(">H", payload[:2])[0]
            ok = version in (1, 2)
            if ok:
                self.protocol = version
            self._reply(VERSION, struct.pack(">B", int(ok)))
        elif cmd == CONTROL_VERSION:
            self._reply(CONTROL_VERSION, struct.pack(">IIII", *c.version))
        elif cmd == SETUP_OUTPUTS:
            freq, text = (struct.unpack(">d", payload[:8])[0], payload[8:]) if self.protocol >= 2 else (125.0, payload)
            names = [n for n in text.decode("ascii", "replace").split(",") if n]
            types = [output_type(n) or "NOT_FOUND" for n in names]
            ok = bool(names) and "NOT_FOUND" not in types and freq > 0
            if ok:  # streamed at most at the control rate (a CB3 sends 125 Hz whatever is asked)
                self.outputs, self.frequency = (names, types, struct_format(types)), min(freq, c.max_frequency)
            c.log("setup_outputs", {"frequency": freq, "names": names, "accepted": ok})
            self._reply(SETUP_OUTPUTS, struct.pack(">B", 1 if ok else 0) + ",".join(types).encode())
        elif cmd == SETUP_INPUTS:
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            types = [input_type(n) or "NOT_FOUND" for n in names]
            types = [t if t == "NOT_FOUND" or c.claim_input(self, n, dry_run=True) else "IN_USE"
                     for n, t in zip(names, types)]
            ok = bool(names) and not {"NOT_FOUND", "IN_USE"} & set(types) and len(self.inputs) < 255
            if ok:
                for n in names:
                    c.claim_input(self, n)
                self.inputs.append((names, types, struct_format(types)))
            self._reply(SETUP_INPUTS, struct.pack(">B", len(self.inputs) if ok else 0) + ",".join(types).encode())
        elif cmd in (START, PAUSE):
            self.started = cmd == START
            self.next_due = time.monotonic()
            c.log("start" if self.started else "pause", None)
            self._reply(cmd, struct.pack(">B", 1))
        elif cmd == DATA:
            rid = payload[0]
            if 1 <= rid <= len(self.inputs):
                names, types, fmt = self.inputs[rid - 1]
                c.write_inputs(names, _group(types, fmt.unpack(payload[:fmt.size])[1:]))
        # TEXT and anything else: accepted silently

    def send_data(self, values: dict) -> None:
        """One 'U' package of the output recipe from `values` (name -> value; missing fields are zero)."""
        if not self.started or self.outputs is None or self.closed:
            return
        names, types, fmt = self.outputs
        flat = [1]
        for n, t in zip(names, types):
            v = values.get(n)
            v = default_value(t) if v is None else v
            if isinstance(v, (tuple, list)):
                flat.extend(v)
            else:
                flat.append(v)
        try:
            self._reply(DATA, fmt.pack(*flat))
        except (OSError, struct.error):
            self.close()

    def _reply(self, cmd: int, payload: bytes) -> None:
        with self.send_lock:
            send_message(self.sock, cmd, payload)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.controller.release_inputs(self)
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self.sock.close()


def _group(types: list[str], flat: tuple) -> list:
    """Regroup unpacked values by field: vectors become tuples."""
    out, i = [], 0
    for t in types:
        n = _SIZES[t]
        out.append(flat[i] if n == 1 else tuple(flat[i:i + n]))
        i += n
    return out
