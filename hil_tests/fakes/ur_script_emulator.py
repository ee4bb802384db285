"""Emulation of ur_rtde's control script (`rtde_control.script`, "RTDE Control Script Loaded (14.02.2024-12:23)" in
ur_rtde 1.6) on the fake UR controller, driving the arm twin.

The fake does not interpret URScript. ur_rtde uploads this program to port 30003 and then talks to it only
through RTDE registers, so the fake replays the program's register protocol (read from the script's source):

* the main loop runs once per controller cycle (`sync()`), reading the command id from
  input_int_register_0 (+ the register offset the client injected: `reg_offset_int = 0` or 24);
* real-time commands (servoJ 11, speedJ 9, ... the script's list) are processed and answered with
  output_int_register_0 = 1 (ready) every cycle they are present;
* any other command runs once (blocking the main loop, e.g. a synchronous movej), then the script writes
  output_int_register_0 = 2 (done) and waits for the client to clear the command (0), answering 1 (ready);
* command arguments: input_double_register_0..5 = q / qd / pose, 6 = velocity or acceleration, 7 = acceleration
  or time, 8..10 = servo time, lookahead time, gain; input_int_register_1 = async flag;
* asynchronous moves report progress in output_int_register_2 (bit 15 running, bits 24-30 operation id,
  bits 16-22 write count), as the script's write_async_progress_register();
* 35 arms the controller's RTDE watchdog on input_int_register_0 with action "stop"; 255 ends the script.

Mapping to the twin (sim/twins/arm.py): servoj -> servo_j, speedj -> speed_j (the script's speed thread re-issues
speedj, so a `time` > 0 does not end the motion), movej -> move_j, stopl/stopj -> servo_stop / speed_stop / stop.
A URScript runtime error (e.g. an argument the twin rejects, or a command this fake does not emulate) stops
the program, as on the controller. Not emulated: movel/servoL/servoC/force mode/jog/contact detection/custom
scripts (they stop the program with an error naming the command).
"""

from __future__ import annotations

import re
import threading

import numpy as np

READY, DONE, STOP_SCRIPT = 1, 2, 255
RT_COMMANDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
NAMES = {1: "movej", 9: "speedj", 11: "servoj", 15: "speed_stop", 16: "servo_stop", 17: "set_payload",
         29: "set_tcp", 31: "protective_stop", 33: "stopl", 34: "stopj", 35: "set_watchdog", 255: "stop_script"}


class ControlScriptEmulator:
    """One run of the uploaded control script. `core` provides rig, sync(program), write_output(name, value),
    set_watchdog(var, freq), log(event, detail), program_finished(program, reason), script_error(program, exc)."""

    def __init__(self, core, script: str):
        self.core, self.arm = core, core.rig.arm
        m_int = re.search(r"reg_offset_int\s*=\s*(\d+)", script)
        m_float = re.search(r"reg_offset_float\s*=\s*(\d+)", script)
        self.int_offset = int(m_int.group(1)) if m_int else 0
        self.float_offset = int(m_float.group(1)) if m_float else 0
        self.alive = True
        # names of the commands the script executed, in order (input registers keep their values across
        # programs: a command a client left there is executed by the next script that starts)
        self.commands: list[str] = []
        self._wr_count = self._op_id = 0
        self._move_token: object | None = None
        self._thread = threading.Thread(target=self._main, name="fake-ur-control-script", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def kill(self) -> None:
        self.alive = False
        self._move_token = None

    # -- registers -------------------------------------------------------------------------------------------
    def _int(self, regs: dict, k: int) -> int:
        return int(regs.get(f"input_int_register_{k + self.int_offset}", 0))

    def _dbl(self, regs: dict, k: int) -> float:
        return float(regs.get(f"input_double_register_{k + self.float_offset}", 0.0))

    def _vec(self, regs: dict, k: int) -> np.ndarray:
        return np.array([self._dbl(regs, k + j) for j in range(6)])

    def _out(self, k: int, value: int) -> None:
        if self.alive:
            self.core.write_output(f"output_int_register_{k + self.int_offset}", int(value))

    def _progress(self, value: int) -> None:
        """write_async_progress_register(): >= 0 running with progress `value` (0 starts a new operation)."""
        self._wr_count = 0 if self._wr_count + 1 > 127 else self._wr_count + 1
        if value == 0:
            self._op_id = 0 if self._op_id + 1 > 127 else self._op_id + 1
        reg = self._wr_count * 65536 + self._op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out(2, reg)

    # -- main loop -------------------------------------------------------------------------------------------
    def _main(self) -> None:
        try:
            self._progress(-1)  # reset_async_progress()
            self._out(0, READY)
            executing = False
            while self.alive:
                regs = self.core.sync(self)
                if regs is None:
                    break
                cmd = self._int(regs, 0)
                if cmd in RT_COMMANDS:
                    self._process(cmd, regs)
                    self._out(0, READY)
                elif cmd == 0:
                    executing = False
                    self._out(0, READY)
                elif not executing:
                    executing = True
                    if not self._process(cmd, regs):
                        break
        except Exception as exc:  # a URScript runtime error stops the program
            self.core.script_error(self, exc)
            return
        self.core.program_finished(self, "the control script ended (stopScript)" if self.alive else "killed")

    def _process(self, cmd: int, regs: dict) -> bool:
        self.commands.append(NAMES.get(cmd, str(cmd)))
        arm = self.arm
        if cmd == 11:
            arm.servo_j(self._vec(regs, 0), self._dbl(regs, 6), self._dbl(regs, 7), self._dbl(regs, 8),
                        self._dbl(regs, 9), self._dbl(regs, 10))
        elif cmd == 9:
            arm.speed_j(self._vec(regs, 0), self._dbl(regs, 6), 0.0)
        elif cmd == 1:
            q, vel, acc = self._vec(regs, 0), self._dbl(regs, 6), self._dbl(regs, 7)
            self._stop_async_move()
            if self._int(regs, 1) == 1:
                self._start_async_move(q, vel, acc)
            else:
                arm.move_j(q, vel, acc)
        elif cmd == 15:
            arm.speed_stop(self._dbl(regs, 0))
        elif cmd == 16:
            arm.servo_stop(self._dbl(regs, 0))
        elif cmd in (33, 34):  # asynchronous stops are executed synchronously here
            self._stop_async_move()
            arm.stop(self._dbl(regs, 0))
        elif cmd == 35:
            self.core.set_watchdog(f"input_int_register_{self.int_offset}", self._dbl(regs, 0))
        elif cmd in (17, 29):
            self.core.log(NAMES[cmd], [self._dbl(regs, k) for k in range(6 if cmd == 29 else 4)])
        elif cmd == 31:
            self.core.rig.trigger_protective_stop("protective_stop() called by the control script")
        elif cmd == STOP_SCRIPT:
            return False
        else:
            raise NotImplementedError(f"control-script command {cmd} is not emulated by the fake controller")
        if cmd not in RT_COMMANDS and self.alive:
            self._out(0, DONE)
        return True

    def _start_async_move(self, q: np.ndarray, vel: float, acc: float) -> None:
        token = self._move_token = object()
        self._progress(0)

        def run():
            try:
                self.arm.move_j(q, vel, acc)
            except Exception as exc:
                self.core.script_error(self, exc)
            if self._move_token is token and self.alive:
                self._move_token = None
                self._progress(-1)

        threading.Thread(target=run, name="fake-ur-move-thread", daemon=True).start()

    def _stop_async_move(self) -> None:
        if self._move_token is not None:  # kill move_thrd; the finished signal comes from here
            self._move_token = None
            self._progress(-1)
