"""Stop conditions and command intake: whether this cycle follows a command or the stop policy.

Stop conditions (`StopConditions.check`), evaluated first every cycle:

* a malformed measurement (NaN/Inf, wrong shape);
* tracking error: the measured joints farther than `max_tracking_error` from the commanded ones (any joint).
  It latches until the error is back under half the limit (hysteresis), so a marginal arm does not chatter;
* the stop state machine (e-stop latched, protective stop and its recovery);
* a resume (e-stop reset / recovery confirmed): the filter first finishes its stop, then restarts the
  commanded stream from the measured joints (`resynced`), so it never jumps to where it stopped commanding.

Command intake (`read_command`): the joint target and/or TCP target are validated (safety.inputs) and the
command's time stamp checked by the watchdog (stale, out of order, from the future). Only a valid, fresh
command is followed. Every reason not to follow is reported as an event.
"""

from __future__ import annotations

from safety.inputs import parse_pose, vec6
from safety.watchdog import FRESH


class StopConditions:
    def __init__(self, max_tracking_error: float, stops, events, stream):
        self.max_track = float(max_tracking_error)
        self.stops = stops
        self.events = events
        self.stream = stream
        self.tracking_fault = False

    def check(self, mq, now: float) -> tuple[bool, str, bool]:
        """(stop, stop state, resynced) for measured joints mq (None if malformed)."""
        ev, stream = self.events, self.stream
        stop = False
        if mq is None:
            ev.report("malformed_measurement", now)
            stop = True
        else:
            q = stream.q
            err = 0.0
            for i in range(6):
                e = mq[i] - q[i]
                if e < 0.0:
                    e = -e
                if e > err:
                    err = e
            if err > self.max_track:
                self.tracking_fault = True
            elif self.tracking_fault and err < 0.5 * self.max_track:
                self.tracking_fault = False
            if self.tracking_fault:
                ev.report("tracking_error", now, value=err, limit=self.max_track)
                stop = True
        stops = self.stops
        if stops.protective:
            stops.update(now)
        state = stops.state
        if state != "running":
            ev.report(state, now)
            stop = True
        resynced = False
        if stops.resumed and not stop:
            if any(stream.v) or any(stream.a):
                stop = True  # finish the stop first, then restart from the measured joints
            else:
                stops.resumed = False
                if mq is not None:
                    stream.reset(mq)
                    resynced = True
        return stop, state, resynced


def read_command(desired_q, desired_tcp, now: float, command_time: float, watchdog, events):
    """(joint target or None, TCP pose or None, follow): follow is True for a valid, fresh command."""
    ev = events
    cmd = None
    pose_cmd = None
    if desired_q is not None:
        cmd = vec6(desired_q)
        if cmd is None:
            ev.report("malformed_command", now)
    if desired_tcp is not None:
        pose_cmd = parse_pose(desired_tcp)
        if pose_cmd is None:
            ev.report("malformed_command", now, message="TCP target is not a valid pose")
    valid = (cmd is not None or (desired_q is None and pose_cmd is not None)) and \
        (desired_tcp is None or pose_cmd is not None)
    if desired_q is None and desired_tcp is None:
        ev.report("malformed_command", now, message="no target given")
    status = watchdog.check(now, command_time)
    if status != FRESH:
        if status == "invalid":
            ev.report("malformed_command", now, message="command time or clock is not a finite number")
        else:
            ev.report(status + "_command", now, value=now - command_time if status != "out_of_order"
                      else watchdog.last_time - command_time,
                      limit=watchdog.max_age if status == "stale" else 0.0)
    return cmd, pose_cmd, valid and status == FRESH


__all__ = ["StopConditions", "read_command"]
