"""The bus's key layout: every topic's key, message type and QoS class, decided here once.

Key layout (``<robot>`` = BusConfig.robot; topics are given relative, e.g. ``bus.publisher("arm/state")``):

    ====================================  ===============  ========================================
    key                                   message          QoS
    ====================================  ===============  ========================================
    sudd/<robot>/camera/<name>/color      CameraFrame      image: DATA, drop, SHM for large frames
    sudd/<robot>/camera/<name>/depth      CameraFrame      image (depth-only frames)
    sudd/<robot>/arm/state                RobotState       control: INTERACTIVE_HIGH, drop, express
    sudd/<robot>/gripper/state            GripperStatus    control
    sudd/<robot>/policy/chunk             ActionChunk      control
    sudd/<robot>/command/language         LanguageCommand  event: INTERACTIVE_LOW, block, express
    sudd/<robot>/safety/event             StatusEvent      event
    sudd/<robot>/safety/estop             StatusEvent      estop: REAL_TIME, block, express
    sudd/<robot>/telemetry/<stage>        Telemetry        telemetry: DATA_LOW, drop
    ====================================  ===============  ========================================

Drop semantics: Zenoh's DROP discards what does not fit the transmit queue (after ~1 ms); consumers read
images with `latest()`, a one-slot mailbox that always holds the newest, so the consumer sees drop-oldest.
Control state is also "newest wins". What must arrive blocks instead: the estop, and the rare, small events and
operator commands (a protective-stop report dropped because the arm-state lane was momentarily full would
leave the console silent). Each blocking class has a priority lane of its own, because Zenoh queues all of
one priority in one pipeline and a blocked message stalls everything behind it in that lane.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import zenoh

from runtime import messages as m

ROOT = "sudd"
ARM_STATE, GRIPPER_STATE, POLICY_CHUNK = "arm/state", "gripper/state", "policy/chunk"
LANGUAGE_COMMAND, SAFETY_EVENT, ESTOP = "command/language", "safety/event", "safety/estop"


def camera_color(name: str) -> str:
    return f"camera/{name}/color"


def camera_depth(name: str) -> str:
    return f"camera/{name}/depth"


def telemetry(stage: str) -> str:
    return f"telemetry/{stage}"


@dataclass(frozen=True)
class QoS:
    priority: zenoh.Priority
    congestion: zenoh.CongestionControl
    express: bool  # send at once, no batching: lower latency for small messages
    shm: bool  # publish through shared memory (when the session has it) above SHM_MIN_BYTES


_CTRL = QoS(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, True, False)
QOS = {"image": QoS(zenoh.Priority.DATA, zenoh.CongestionControl.DROP, False, True), "control": _CTRL,
       "estop": QoS(zenoh.Priority.REAL_TIME, zenoh.CongestionControl.BLOCK, True, False),
       "event": QoS(zenoh.Priority.INTERACTIVE_LOW, zenoh.CongestionControl.BLOCK, True, False),
       "telemetry": QoS(zenoh.Priority.DATA_LOW, zenoh.CongestionControl.DROP, False, False)}
# relative topic pattern -> (message type, QoS class); {x} is one key segment
TOPICS = {"camera/{name}/color": (m.CameraFrame, "image"), "camera/{name}/depth": (m.CameraFrame, "image"),
          ARM_STATE: (m.RobotState, "control"), GRIPPER_STATE: (m.GripperStatus, "control"),
          POLICY_CHUNK: (m.ActionChunk, "control"), LANGUAGE_COMMAND: (m.LanguageCommand, "event"),
          SAFETY_EVENT: (m.StatusEvent, "event"), ESTOP: (m.StatusEvent, "estop"),
          "telemetry/{stage}": (m.Telemetry, "telemetry")}
SHM_MIN_BYTES = 32 * 1024  # below this a copy over the socket is as fast as a shared-memory handle
SEGMENT = re.compile(r"[A-Za-z0-9_-]{1,64}")  # one key segment: a robot, camera or stage name


def resolve_topic(topic: str, wildcard: bool = False) -> tuple[type[m.Message], QoS]:
    """The message type and QoS of a relative topic; ValueError naming the known topics if it is none."""
    parts = topic.split("/")
    for pattern, (mtype, qos) in TOPICS.items():
        pat = pattern.split("/")
        if len(pat) == len(parts) and all(
                p == s if not p.startswith("{") else (SEGMENT.fullmatch(s) or (wildcard and s == "*"))
                for p, s in zip(pat, parts)):
            return mtype, QOS[qos]
    raise ValueError(f"unknown topic {topic!r}; known: {', '.join(TOPICS)} (segments: letters, digits, _ -)")
