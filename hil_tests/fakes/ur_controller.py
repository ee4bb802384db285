"""FakeURController: a fake UR controller on loopback that the real ur_rtde client connects to, with a simulated
UR5e (e-Series, 500 Hz) or UR5 (CB3, 125 Hz) behind it (`SimRig(world, "realtime")` from sim.twins).

Why a separate process: ur_rtde's Python bindings hold the GIL inside every call (a constructor waiting for the
first RTDE package, a blocking moveJ, the spin loops of sendCommand), so a server in the test's own process
would never get to answer. `FakeURController` (test side) starts `python -m hil_tests.fakes.ur_controller`
and talks to it over JSON lines on stdin/stdout (fault injection, twin state, event log).

Ports: ur_rtde hard-codes them (RTDE 30004 in both interfaces, dashboard 29999 and script 30003 by default), so
every fake binds the fixed ports on its own random loopback address 127.a.b.c (Linux routes all of 127/8 to lo):
parallel tests and test runs never collide, and no pytest marks are needed. Served:

* 30004 RTDE (ur_rtde_protocol.py): version negotiation, controller version, output/input recipes with the
  guide's types (NOT_FOUND / IN_USE as the controller answers), data packages at each recipe's frequency;
* 30002/30003 script ports: a program (`def ...():` through a column-0 `end`) replaces the running one;
  ur_rtde's control script is emulated through its register protocol (ur_script_emulator.py);
* 29999 dashboard: the lines ur_rtde sends (PolyscopeVersion, get serial number, is in remote control,
  unlock protective stop, close safety popup, stop, popup, robotmode, safetystatus, running, programState).

Controller behaviour: ur_controller_core.py. Not modelled: the state streams the real 30001-30003 ports send
(ur_rtde never reads them), the speed slider's effect on motion, movel/servoL/force mode and the like.
"""

from __future__ import annotations

import json
import os
import queue
import random
import subprocess
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
E_SERIES, CB3 = (5, 11, 1, 108318), (3, 15, 7, 106331)


class FakeURController:
    """Test-side handle. `series` "e-series" (UR5e twin, PolyScope 5.11, 500 Hz) or "cb3" (UR5 twin, 3.15, 125 Hz)."""

    def __init__(self, series: str = "e-series", unlock_delay_s: float = 5.0, remote_control: bool = True,
                 start_timeout_s: float = 60.0):
        if series not in ("e-series", "cb3"):
            raise ValueError(f"series = {series!r}; expected 'e-series' or 'cb3'")
        self.series = series
        self._lock = threading.Lock()
        self._lines: queue.Queue = queue.Queue()
        for _ in range(5):  # a random loopback address whose fixed ports happen to be taken: draw again
            self.host = f"127.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(2, 254)}"
            cfg = dict(host=self.host, version=E_SERIES if series == "e-series" else CB3,
                       variant="ur5e" if series == "e-series" else "ur5", unlock_delay_s=unlock_delay_s,
                       remote_control=remote_control)
            env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"),
                       PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
            self._proc = subprocess.Popen([sys.executable, "-m", "hil_tests.fakes.ur_controller", json.dumps(cfg)],
                                          cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            threading.Thread(target=self._read, args=(self._proc, self._lines), daemon=True).start()
            reply = self._next(start_timeout_s)
            if "ready" in reply:
                self.info = reply["ready"]
                return
            self._proc.wait(timeout=5)
        raise RuntimeError(f"the fake UR controller did not start: {reply}")

    @staticmethod
    def _read(proc, lines) -> None:
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    def _next(self, timeout: float) -> dict:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"the fake UR controller did not answer within {timeout} s") from None
        if line is None:
            raise RuntimeError(f"the fake UR controller exited (code {self._proc.poll()})")
        return json.loads(line)

    def _rpc(self, op: str, *args, timeout: float = 10.0):
        with self._lock:
            self._proc.stdin.write(json.dumps({"op": op, "args": args}) + "\n")
            self._proc.stdin.flush()
            reply = self._next(timeout)
        if "error" in reply:
            raise RuntimeError(f"fake UR controller: {op} failed: {reply['error']}")
        return reply["ok"]

    # fault injection and observation (see ControllerCore.rpc_*)
    def state(self) -> dict:
        return self._rpc("state")

    def events(self) -> dict:
        return self._rpc("events")

    def trigger_protective_stop(self, reason: str = "injected fault") -> None:
        self._rpc("trigger_protective_stop", reason)

    def drop_network(self) -> None:
        self._rpc("drop_network")

    def restore_network(self) -> None:
        self._rpc("restore_network")

    def set_speed_slider(self, fraction: float) -> None:
        self._rpc("set_speed_slider", fraction)

    def mute(self, muted: bool = True) -> None:
        """Stop (or resume) sending RTDE data without closing anything, as a pulled cable looks."""
        self._rpc("mute", muted)

    def reset(self) -> None:
        """A rebooted controller: no program, no stop, registers cleared, the arm back at home."""
        self._rpc("reset")

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                self._rpc("close", timeout=10.0)
                self._proc.wait(timeout=10)
            except (OSError, RuntimeError, TimeoutError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait(timeout=5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _child_main(cfg: dict) -> None:
    rpc_out = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # anything else printed goes to stderr, keeping stdout for the RPC replies
    sys.stdout = sys.stderr
    try:
        from hil_tests.fakes.ur_controller_core import ControllerCore

        core = ControllerCore(**cfg)
        core.start()
    except Exception as exc:
        rpc_out.write(json.dumps({"error": repr(exc)}) + "\n")
        return
    rpc_out.write(json.dumps({"ready": {"host": core.host, "version": core.version, "hz": core.max_frequency}}) + "\n")
    for line in sys.stdin:  # EOF (the test process died) ends the controller too
        req = json.loads(line)
        try:
            reply = {"ok": getattr(core, "rpc_" + req["op"])(*req["args"])}
        except Exception as exc:
            reply = {"error": repr(exc)}
        rpc_out.write(json.dumps(reply) + "\n")
        if req["op"] == "close":
            return
    core.rpc_close()


if __name__ == "__main__":
    _child_main(json.loads(sys.argv[1]))
