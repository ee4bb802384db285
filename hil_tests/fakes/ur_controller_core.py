"""ControllerCore: the fake UR controller's inside (runs in the child process started by FakeURController).

One controller loop at the twin's control rate (500 Hz UR5e / 125 Hz UR5) supervises the running program
(protective stop, RTDE watchdog), wakes the emulated control script (its `sync()`) and streams RTDE data
packages to every started client at its recipe's frequency. Client threads serve RTDE (30004), the dashboard
(29999) and the script ports (30002/30003). All controller state is guarded by `lock`.

Behaviour of the real controller modelled here: a protective stop stops the program (runtime_state STOPPED);
the dashboard refuses "unlock protective stop" until `unlock_delay_s` after the stop; a program does not start
while protectively stopped; a new program replaces the running one; the RTDE watchdog (action "stop") stops the
program and brings the arm to rest when its register is not updated in time (a frequency <= 0 disables it:
an assumption, the URScript manual does not say); input registers keep their values across programs (so a
restarted script sees the last command the client left there); an input field belongs to one connection.
"""

from __future__ import annotations

import json
import os
import re
import socket
import struct
import threading
import time
from collections import deque

from hil_tests.fakes.ur_rtde_protocol import RtdeSession
from hil_tests.fakes.ur_script_emulator import ControlScriptEmulator

RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
SAFETY_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP"}
UNLOCK_REFUSED = ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective "
                  "stop before unlocking")


class ControllerCore:
    """The controller, inside the child process."""

    def __init__(self, host, version, variant, unlock_delay_s, remote_control):
        os.environ.setdefault("MUJOCO_GL", "egl")
        from sim.scene import base_scene
        from sim.twins import SimRig
        from sim.twins.rig import ProtectiveStopConfig
        from sim.world import World

        self.host, self.version, self.remote_control = host, tuple(version), remote_control
        world = World(base_scene(variant).compile(), variant)
        self.rig = SimRig(world, "realtime", safety=ProtectiveStopConfig(unlock_delay_s=unlock_delay_s))
        self.period = self.rig.control_period
        self.max_frequency = round(1.0 / self.period)
        self.lock = threading.RLock()
        self._cycle = threading.Condition(self.lock)
        self.cycle_no = 0
        self.inputs: dict = {}
        # The input registers as each cycle latched them, when a client had written since the cycle before: a
        # script thread starved for a few cycles (a loaded CI machine) still sees every write in order, as a
        # real controller's script, never late, does; a speedJ overwritten by the next watchdog kick before the
        # script looked was otherwise lost.
        self._latched: deque = deque(maxlen=500)
        self._last_latched: dict = {}
        self.input_stamp: dict[str, float] = {}
        self._owner: dict = {}
        self.outputs: dict = {}
        self.sessions: list = []
        self.clients: list[socket.socket] = []
        self.listeners: list[socket.socket] = []
        self.program = None
        self.watchdog: tuple[str, float, float] | None = None  # (variable, min frequency, armed at)
        self.slider, self.popup, self.muted = 1.0, False, False
        self.ev = dict(uploads=0, programs=[], dashboard=[], watchdog=[], watchdog_trips=0, program_stops=[],
                       errors=[], setup_outputs=[], log=[])
        self.t0 = time.monotonic_ns()
        self.running = True

    def start(self) -> None:
        self.rig.start()
        self.rpc_restore_network()
        threading.Thread(target=self._loop, name="fake-ur-controller", daemon=True).start()

    # -- the controller cycle ------------------------------------------------------------------------------
    def _loop(self) -> None:
        deadline = time.monotonic()
        while self.running:
            deadline += self.period
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -25 * self.period:
                deadline = time.monotonic()
            now = time.monotonic()
            with self.lock:
                self._supervise(now)
                self.cycle_no += 1
                if self.inputs != self._last_latched:
                    self._last_latched = dict(self.inputs)
                    self._latched.append((self.cycle_no, self._last_latched))
                self._cycle.notify_all()
                due = [s for s in self.sessions if s.started and now >= s.next_due]
            if due and not self.muted:
                values = self._snapshot()
                for s in due:
                    s.next_due = max(s.next_due + 1.0 / s.frequency, now - self.period)
                    s.send_data(values)

    def _supervise(self, now: float) -> None:
        if self.program is None:
            return
        if self.rig.protective_stopped:
            self._stop_program(f"protective stop ({self.rig.stop_reason})", halt=False)
        elif self.watchdog is not None and self.watchdog[1] > 0:
            var, freq, armed = self.watchdog
            if now - max(self.input_stamp.get(var, armed), armed) > 1.0 / freq:
                self.ev["watchdog_trips"] += 1
                self._stop_program(f"RTDE watchdog: {var} not updated at {freq} Hz", halt=True)

    def _stop_program(self, reason: str, halt: bool) -> None:
        self.program.kill()
        self.program, self.watchdog = None, None
        self.ev["program_stops"].append(reason)
        if halt:  # a program stop brings the arm to rest (whatever it was doing)
            threading.Thread(target=self._halt, daemon=True).start()

    def _halt(self) -> None:
        try:
            self.rig.arm.stop(10.0)
        except Exception as exc:
            self.ev["errors"].append(f"halt: {exc!r}")

    def _snapshot(self) -> dict:
        s = self.rig.arm.state()
        with self.lock:
            values = {**self.inputs, **self.outputs}
            playing = self.program is not None
        pstop = s.is_protective_stopped
        values.update(
            timestamp=(self.rig.sample_ns - self.t0) * 1e-9, actual_q=tuple(s.q), actual_qd=tuple(s.qd),
            actual_TCP_pose=tuple(s.tcp_pose), actual_TCP_force=tuple(s.tcp_force), target_TCP_pose=tuple(s.tcp_pose), target_q=tuple(s.target_q),
            robot_mode=int(s.robot_mode), safety_mode=int(s.safety_mode), safety_status=int(s.safety_mode),
            safety_status_bits=(1 << 2 | 1 << 10) if pstop else 1, joint_mode=(253,) * 6,
            runtime_state=RUNTIME_PLAYING if playing else RUNTIME_STOPPED, robot_status_bits=1 | (2 if playing else 0),
            speed_scaling=s.speed_scaling, target_speed_fraction=self.slider, actual_main_voltage=48.0,
            actual_robot_voltage=48.0, joint_temperatures=(30.0,) * 6)
        return values

    # -- services used by the RTDE sessions and the script emulator -----------------------------------------
    def log(self, event: str, detail) -> None:
        self.ev["setup_outputs" if event == "setup_outputs" else "log"].append([event, detail])

    def claim_input(self, session, name: str, dry_run: bool = False) -> bool:
        with self.lock:
            owner = self._owner.get(name)
            if owner is not None and owner is not session and not owner.closed:
                return False
            if not dry_run:
                self._owner[name] = session
            return True

    def release_inputs(self, session) -> None:
        with self.lock:
            self._owner = {n: s for n, s in self._owner.items() if s is not session}
            if session in self.sessions:
                self.sessions.remove(session)

    def write_inputs(self, names, values) -> None:
        now = time.monotonic()
        with self.lock:
            for n, v in zip(names, values):
                self.inputs[n] = v
                self.input_stamp[n] = now
            if self.inputs.get("speed_slider_mask") == 1 and "speed_slider_fraction" in names:
                self.slider = min(1.0, max(0.0, float(self.inputs["speed_slider_fraction"])))

    def write_output(self, name: str, value) -> None:
        with self.lock:
            self.outputs[name] = value

    def sync(self, program):
        """URScript sync(): the input registers as of the next controller cycle after the one this program last
        saw (the oldest latched change it has not seen, when it fell behind); None: killed."""
        with self._cycle:
            seen = getattr(program, "synced_cycle", None)
            if seen is None:  # a new program starts at the next cycle, with what the registers hold then
                seen = self.cycle_no
            self._cycle.wait_for(lambda: self.cycle_no > seen or not program.alive, timeout=1.0)
            if not (program.alive and self.program is program):
                return None
            for cycle, regs in self._latched:
                if cycle > seen:
                    program.synced_cycle = cycle
                    return dict(regs)
            program.synced_cycle = self.cycle_no
            return dict(self.inputs)

    def set_watchdog(self, var: str, freq: float) -> None:
        with self.lock:
            self.watchdog = (var, float(freq), time.monotonic())
            self.ev["watchdog"].append([var, float(freq)])

    def program_finished(self, program, reason: str) -> None:
        with self.lock:
            if self.program is program:
                self._stop_program(reason, halt=True)

    def script_error(self, program, exc: BaseException) -> None:
        self.ev["errors"].append(f"script runtime error: {exc!r}")
        self.program_finished(program, f"runtime error: {exc}")

    def program_received(self, text: str, port: int) -> None:
        with self.lock:
            self.ev["uploads"] += 1
            name = (re.match(r"\s*(?:def|sec)\s+(\w+)", text) or [None, "?"])[1]
            if self.program is not None:
                self._stop_program("replaced by a new program", halt=True)
            if "$" in text:
                self.ev["errors"].append("the uploaded script still holds $-version markers")
            if name != "rtde_control" or "RTDE Control Script" not in text:
                self.ev["programs"].append(dict(name=name, port=port, emulated=False))
                return
            if self.rig.protective_stopped:  # the controller does not start a program while stopped
                self.ev["errors"].append("program not started: the robot is protectively stopped")
                return
            self.program = ControlScriptEmulator(self, text)
            self.ev["programs"].append(dict(name=name, port=port, emulated=True, bytes=len(text),
                                            register_offset=self.program.int_offset))
            self.program.start()

    # -- network ---------------------------------------------------------------------------------------------
    def _listen(self, port: int, handler) -> None:
        sock = socket.create_server((self.host, port))
        self.listeners.append(sock)

        def accept():
            while True:
                try:
                    conn, _ = sock.accept()
                except OSError:
                    return
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", 1, 0))
                with self.lock:
                    self.clients.append(conn)
                threading.Thread(target=handler, args=(conn, port), daemon=True).start()

        threading.Thread(target=accept, name=f"fake-ur-accept-{port}", daemon=True).start()

    def _rtde(self, conn: socket.socket, port: int) -> None:
        session = RtdeSession(conn, self)
        with self.lock:
            self.sessions.append(session)
        session.serve()

    def _script(self, conn: socket.socket, port: int) -> None:
        buf = ""
        with conn:
            while True:
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                buf += data.decode("utf-8", "replace")
                while (m := re.search(r"^end[ \t]*\r?$", buf, re.M)) is not None:
                    program, buf = buf[:m.end()], buf[m.end():]
                    self.program_received(program.strip("\r\n"), port)

    def _dashboard(self, conn: socket.socket, port: int) -> None:
        with conn, conn.makefile("rwb", buffering=0) as f:
            try:
                f.write(b"Connected: Universal Robots Dashboard Server\n")
                for raw in f:
                    line = raw.decode("utf-8", "replace").strip()
                    reply = self._dashboard_reply(line)
                    self.ev["dashboard"].append([line, reply])
                    f.write(reply.encode() + b"\n")
                    if line == "quit":
                        return
            except OSError:
                return

    def _dashboard_reply(self, line: str) -> str:
        cmd = line.lower()
        e_series = self.version[0] >= 5
        playing = self.program is not None
        if cmd == "polyscopeversion":
            return "URSoftware {}.{}.{}.{} (Mar 22 2021)".format(*self.version)
        if cmd == "get serial number" and e_series:
            return "20185500020"
        if cmd == "is in remote control" and e_series:
            return "true" if self.remote_control else "false"
        if cmd == "unlock protective stop":
            return "Protective stop releasing" if self.rig.arm.unlock_protective_stop() else UNLOCK_REFUSED
        if cmd == "close safety popup":
            self.popup = False
            return "closing safety popup"
        if cmd in ("robotmode", "safetystatus", "safetymode"):
            mode = 3 if self.rig.protective_stopped else 1
            label = {"robotmode": "Robotmode", "safetystatus": "Safetystatus", "safetymode": "Safetymode"}[cmd]
            return f"{label}: {'RUNNING' if cmd == 'robotmode' else SAFETY_NAMES[mode]}"
        if cmd == "stop":
            with self.lock:
                if self.program is None:
                    return "Failed to execute: stop"
                self._stop_program("dashboard stop", halt=True)
            return "Stopped"
        if cmd == "running":
            return f"Program running: {str(playing).lower()}"
        if cmd == "programstate":
            return "PLAYING rtde_control" if playing else "STOPPED <unnamed>"
        if cmd.startswith("popup "):
            return "showing popup"
        if cmd == "close popup":
            return "closing popup"
        if cmd == "quit":
            return "Disconnected"
        return f"could not understand: '{line}'"

    # -- RPC (test side) ------------------------------------------------------------------------------------
    def rpc_state(self) -> dict:
        s = self.rig.arm.state()
        with self.lock:
            prog = self.program
            return dict(q=s.q.tolist(), qd=s.qd.tolist(), target_q=s.target_q.tolist(), mode=self.rig.arm._mode,
                        protective_stopped=self.rig.protective_stopped, program_running=prog is not None,
                        commands=list(prog.commands) if prog else [],
                        watchdog=list(self.watchdog[:2]) if self.watchdog else None, slider=self.slider,
                        popup=self.popup, sessions=len(self.sessions))

    def rpc_events(self) -> dict:
        with self.lock:
            return json.loads(json.dumps(self.ev))

    def rpc_trigger_protective_stop(self, reason: str) -> None:
        self.rig.trigger_protective_stop(reason)
        self.popup = True

    def rpc_set_speed_slider(self, fraction: float) -> None:
        self.slider = float(fraction)

    def rpc_mute(self, muted: bool) -> None:
        self.muted = bool(muted)

    def rpc_reset(self) -> None:
        rig = self.rig
        with self.lock, rig.lock:
            if self.program is not None:
                self._stop_program("controller reset", halt=False)
            self.inputs.clear()
            self.outputs.clear()
            self.slider, self.popup, self.muted = 1.0, False, False
            rig.reset()

    def rpc_drop_network(self) -> None:
        with self.lock:
            socks, self.listeners, self.clients = self.listeners + self.clients, [], []
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def rpc_restore_network(self) -> None:
        for port, handler in ((30004, self._rtde), (29999, self._dashboard), (30002, self._script),
                              (30003, self._script)):
            self._listen(port, handler)

    def rpc_close(self) -> None:
        self.running = False
        self.rpc_drop_network()
        self.rig.close()
