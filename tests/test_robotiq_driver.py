"""Robotiq2F85 against FakeRobotiqServer: the URCap socket protocol over loopback TCP, with a simulated 2F-85.

Covers the protocol (lines sent, `ack`, replies with and without newline), activation, register mapping,
object detection, argument checks, and the failure paths: malformed replies, silent server, dropped
connection (ConnectionError, then a transparent reconnect), no server at all. The shared GripperDriver
contract runs on the same pair as `robotiq-loopback` in test_device_contract.py.
"""

from __future__ import annotations

import socket
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # hil_tests is not installed; bare `pytest` too
from hil_tests.fakes.robotiq_server import FakeRobotiqServer  # noqa: E402
from runtime.drivers.robotiq import GripperStateError, Robotiq2F85, RobotiqConfig, RobotiqProtocolError  # noqa: E402
from sim.devices import GripperDriver  # noqa: E402

# A controller twin keeps the robot's clock in another process: run alone, not beside other tests (`make test` runs
# the realtime tests after the rest; under a second loaded worker a 500 Hz servo stream missed its period).
pytestmark = pytest.mark.realtime


@pytest.fixture
def server():
    with FakeRobotiqServer(speed_scale=5.0, activation_s=0.05) as s:
        yield s


def _gripper(server, **kw) -> Robotiq2F85:
    kw.setdefault("timeout", 0.5)
    return Robotiq2F85(RobotiqConfig(*server.address, **kw))


@pytest.fixture
def gripper(server):
    g = _gripper(server)
    yield g
    g.disconnect()


def _sets(server) -> list[str]:
    return [r for r in server.requests if r.startswith("SET")]


def test_activation_sequence_and_refusal_before_it(server, gripper):
    assert isinstance(gripper, GripperDriver)
    assert gripper.move(1.0) is False and gripper.close() is False  # refused before activate(), nothing sent
    assert _sets(server) == []
    assert not gripper.state().is_activated
    gripper.activate()
    assert _sets(server) == ["SET ACT 0 ATR 0", "SET ACT 1"]
    assert server.regs["STA"] == 3 and gripper.state().is_activated
    second = _gripper(server)  # already active without a fault: no reset (it would drop a held object)
    second.activate()
    assert _sets(server) == ["SET ACT 0 ATR 0", "SET ACT 1"]
    second.disconnect()


def test_activation_timeout_is_a_clear_error(server):
    server.activation_hangs = True
    g = _gripper(server, activation_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match=r"activation \(ACT 1\) \(STA=1, FLT=0\).*pendant"):
        g.activate()
    assert time.monotonic() - t0 < 1.0
    assert g.move(0.5) is False


def test_open_close_and_register_mapping(server):
    server.closed_limit = 228  # this gripper's fingers meet at register 228
    g = _gripper(server, open_register=3, closed_register=228)
    g.activate()
    assert g.close(speed=1.0, force=0.0) is True
    assert _sets(server)[-1] == "SET POS 228 SPE 255 FOR 0 GTO 1"
    s = g.state()
    assert s.position == 1.0 and s.target == 1.0 and not s.is_moving and not s.object_detected
    assert g.move(0.5, speed=0.0, force=1.0) is True
    assert _sets(server)[-1] == "SET POS 116 SPE 0 FOR 255 GTO 1"  # 3 + 0.5 * 225, rounded
    assert abs(g.state().position - 0.5) < 0.01 and server.regs["PRE"] == 116
    assert g.open(speed=1.0) is True
    assert g.state().position == 0.0 and server.regs["POS"] == 3


def test_move_without_wait_returns_while_moving(server, gripper):
    gripper.activate()
    t0 = time.monotonic()
    assert gripper.move(1.0, speed=0.0, wait=False) is True
    assert time.monotonic() - t0 < 0.1
    time.sleep(0.05)
    s = gripper.state()
    assert s.is_moving and 0.0 < s.position < 1.0 and s.target == 1.0
    assert gripper.close(speed=1.0)  # a new request while moving; wait=True waits for PRE, then OBJ
    assert gripper.state().position == 1.0 and not gripper.state().is_moving


def test_object_detection_closing_and_opening(server, gripper):
    gripper.activate()
    gripper.open(speed=1.0)
    server.place_object(100)
    assert gripper.close(speed=1.0) is True
    s = gripper.state()
    assert s.object_detected and not s.is_moving and abs(s.position - 100 / 255) < 0.01 and s.target == 1.0
    assert server.regs["OBJ"] == 2
    assert gripper.open(speed=1.0) and not gripper.state().object_detected
    gripper.close(speed=1.0)
    server.place_object(60, outer=True)  # something outside the fingers: opening stops on it
    assert gripper.open(speed=1.0)
    s = gripper.state()
    assert s.object_detected and server.regs["OBJ"] == 1 and abs(s.position - 60 / 255) < 0.01


@pytest.mark.parametrize("kwargs, match", [
    (dict(position=1.2), r"position = 1.2 is out of range; allowed: \[0.0, 1.0\]"),
    (dict(position=0.5, speed=-0.1), r"speed .*\[0.0, 1.0\]"),
    (dict(position=0.5, force=2), r"force .*\[0.0, 1.0\]"),
    (dict(position=float("nan")), "position"),
    (dict(position="closed"), "position must be a number"),
])
def test_bad_arguments_raise_before_anything_is_sent(server, gripper, kwargs, match):
    gripper.activate()
    n = len(server.requests)
    with pytest.raises(ValueError, match=match):
        gripper.move(**kwargs)
    assert len(server.requests) == n


def test_config_validation():
    with pytest.raises(ValueError, match="closed_register"):
        RobotiqConfig("h", open_register=200, closed_register=100)
    with pytest.raises(ValueError, match="port"):
        RobotiqConfig("h", port=0)


@pytest.mark.parametrize("reply", [b"POS banana\n", b"OBJ 3\n", b"ack", b"POS\n", b"POS 1 2\n"])
def test_malformed_get_reply_is_an_error_then_recovers(server, gripper, reply):
    gripper.activate()
    server.reply_hook = lambda line: reply if line == "GET POS" else server.handle(line)
    with pytest.raises(RobotiqProtocolError, match="GET POS"):
        gripper.state()
    server.reply_hook = None
    assert gripper.state().is_activated  # reconnected: a stale reply is never read as a new answer


def test_set_without_ack_is_an_error(server, gripper):
    gripper.activate()
    server.reply_hook = lambda line: b"nak" if line.startswith("SET") else server.handle(line)
    with pytest.raises(RobotiqProtocolError, match=r"expected 'ack' to 'SET POS 255 SPE 128 FOR 128 GTO 1', got 'nak'"):
        gripper.close()


def test_question_mark_reply_is_a_state_error(server, gripper):
    server.reply_hook = lambda line: b"STA ?\n" if line == "GET STA" else server.handle(line)
    with pytest.raises(GripperStateError, match="emergency stop"):
        gripper.state()


def test_get_reply_without_newline_is_accepted(server, gripper):
    server.reply_hook = lambda line: server.handle(line).rstrip(b"\n")
    gripper.activate()
    assert gripper.close(speed=1.0) and gripper.state().position == 1.0


def test_silent_server_times_out_without_hanging(server):
    g = _gripper(server, timeout=0.2)
    server.reply_hook = lambda line: None
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match=r"no reply to 'GET STA' within 0.2 s"):
        g.activate()
    assert time.monotonic() - t0 < 0.6
    server.reply_hook = None
    g.activate()
    g.disconnect()


def test_move_timeout_when_fingers_never_stop(server):
    g = _gripper(server, move_timeout_s=0.2)
    g.activate()
    server.speed_scale = 1e-3  # the fingers barely move
    with pytest.raises(TimeoutError, match=r"fingers to stop \(POS 255\)"):
        g.close(speed=0.0)
    g.disconnect()


def test_dropped_connection_raises_then_reconnects(server, gripper):
    gripper.activate()
    gripper.close(speed=1.0)
    server.drop_connections()
    with pytest.raises(ConnectionError, match="connection lost"):
        gripper.state()
    s = gripper.state()  # reconnects on the next call; the gripper kept its state
    assert s.is_activated and s.position == 1.0
    assert gripper.open(speed=1.0) and gripper.state().position == 0.0


def test_gripper_reset_behind_the_drivers_back_refuses_moves(server, gripper):
    gripper.activate()
    server.handle("SET ACT 0")  # e.g. reset from the pendant
    assert gripper.move(0.5) is False
    gripper.activate()
    assert gripper.move(0.5) is True


def test_no_server_is_a_connection_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here once closed
    g = Robotiq2F85(RobotiqConfig("127.0.0.1", port=port, timeout=0.5))
    with pytest.raises(ConnectionError, match=rf"cannot connect to the Robotiq URCap server at 127.0.0.1:{port}"):
        g.state()


@pytest.mark.parametrize("holding", [False, True])
def test_the_controller_reopens_an_empty_close_over_the_real_protocol(server, gripper, holding):
    """The controller's gripper channel (runtime.controller.gripper) on this driver: it reads the gOBJ verdict
    over the socket and undoes a close on nothing; a close on an object stands."""
    from runtime.controller import ControllerConfig
    from runtime.controller.gripper import GripperChannel
    from safety import default_limits
    from safety.events import EventCoalescer

    gripper.activate()
    gripper.open(speed=1.0)
    if holding:
        server.place_object(100)
    channel = GripperChannel(gripper, default_limits("ur5e"), ControllerConfig(reopen_hold=0.5))
    events = EventCoalescer()
    channel.update(0.0, 0.0, True, events)  # the first value sets the state (open)
    t0 = time.monotonic()
    sent = []
    while time.monotonic() - t0 < 2.0:  # the policy says "closed" throughout, at ~100 Hz
        r = channel.update(0.9, time.monotonic() - t0 + 0.01, True, events)
        if r is not None:
            sent.append(r)
        time.sleep(0.01)
    if holding:
        assert sent == [True] and channel.empty_closes == 0 and gripper.state().object_detected
    else:  # closed, found empty, opened, held open 0.5 s, closed again as the policy still asks, ...
        assert sent[:3] == [True, False, True] and channel.empty_closes >= 1
        assert "closed on nothing" in "".join(e.message for e in events.flush(10.0))
