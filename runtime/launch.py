"""Launch the runtime: node processes with their configs, ready waits, monitoring and the ordered shutdown.

    from runtime.launch import Launcher, sim_stack
    with Launcher(sim_stack(bundle="policy/bundles/multitask", task="pick_place", seed=0)) as la:
        la.wait_ready()
        la.say("put the red block in the left bin")
        la.monitor(duration_s=20)
    print(la.reports)

Process layout: this process (the launcher) holds the bus *hub*, a Zenoh session listening on `hub`
(default tcp/127.0.0.1:7447; `sudd say --connect` joins there), and starts every node as a `spawn`
multiprocessing child (runtime.nodes.common.process_entry) with its own stop Event; each node opens its own
session, connected to the hub (Zenoh gossip then links the nodes directly). Nodes report "ready" and, at
exit, a report dict on one status queue.

Shutdown, whatever the cause (Ctrl-C / SIGTERM to the launcher, `duration_s` over, or a node that died):
1. the robot node's stop Event is set FIRST: it performs the controlled stop (decelerate through the safety
   filter, servo_stop) and exits; the launcher waits up to `robot_stop_timeout_s` for it;
2. then every other node's stop Event; they exit within a loop period;
3. anything still alive after `grace_s` is terminated (SIGTERM = a stop request in a node), then killed;
4. the hub closes. Nothing is left running (`Launcher.alive()` is empty afterwards).
Node processes ignore SIGINT (Ctrl-C reaches the whole process group; only the launcher orders the stop)
and stop by themselves when the launcher disappears (re-parented). A crashed policy node is not restarted:
the controller already holds the arm when chunks stop (watchdog), and an operator should see why inference
died before the arm moves again; the launcher stops the whole stack (robot first) and reports the crash.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import queue
import signal
import threading
import time
from dataclasses import dataclass

from runtime.nodes.common import HUB_DEFAULT, BusSettings, config_to_dict
from runtime.shaping import Shaping

log = logging.getLogger(__name__)

ROBOT = "robot"


@dataclass
class NodeSpec:
    name: str
    module: str  # runtime.nodes.<x>: has CONFIG and run(cfg, ctx)
    config: object  # an instance of module.CONFIG


class NodeFailed(RuntimeError):
    pass


def _with_bus(cfg, bus: BusSettings):
    return dataclasses.replace(cfg, bus=bus)


def bundle_manifest(path) -> dict:
    """The bundle's manifest.json (plain JSON: the launcher does not load the model)."""
    import json
    from pathlib import Path

    return json.loads((Path(path) / "manifest.json").read_text())


def sim_stack(bundle: str, task: str = "pick_place", seed: int = 0, dr: str = "off", command: str = "",
              robot: str = "ur5", replan_every: int = 1, speed: str = "", goal_query: bool = True,
              phases: bool | None = None, shaping: Shaping = Shaping(), **robot_overrides) -> list[NodeSpec]:
    """robot node (sim twins + cameras matching the bundle) + policy node. The scene keeps the bundle's
    held-out colours/shapes off the target, as its training data and `sudd eval`'s seen suite do. `shaping`: the
    policy node's steps between the denoiser and the controller (runtime/chunk_shaper.py)."""
    from runtime.nodes.policy_node import PolicyNodeConfig
    from runtime.nodes.robot_node import RobotNodeConfig, scene_holdout
    from runtime.sim_cell import sim_cell_ceiling

    man = bundle_manifest(bundle)
    held = man.get("data", {}).get("holdout") or {}  # what its training data kept out (as `sudd eval`)
    rcfg = RobotNodeConfig(**{"task": task, "seed": seed, "dr": dr, "cameras": tuple(man["cameras"]),
                              "image_size": tuple(man["image_size"]), "holdout_colors": tuple(held.get("colors", ())),
                              "holdout_shapes": tuple(held.get("shapes", ())), **robot_overrides})
    # the cell the robot node will declare, for the policy node's free-space pace (runtime/free_pace.py)
    ceiling = sim_cell_ceiling(rcfg.task, rcfg.seed, rcfg.dr, scene_holdout(rcfg), rcfg.limits_file)
    pcfg = PolicyNodeConfig(bundle=str(bundle), command=command, replan_every=replan_every, speed=speed,
                            goal_query=goal_query, phases=phases, cell_ceiling_m=ceiling, **dataclasses.asdict(shaping))
    return [NodeSpec(ROBOT, "runtime.nodes.robot_node", rcfg), NodeSpec("policy", "runtime.nodes.policy_node", pcfg)]


def hardware_stack(bundle: str, robot_ip: str, camera_serials: dict[str, str], allow_motion: bool = False,
                   command: str = "", replan_every: int = 1, speed: str = "", goal_query: bool = True,
                   phases: bool | None = None, **robot_overrides) -> list[NodeSpec]:
    """robot node on URRtdeArm + Robotiq2F85, one camera node per bundle camera, the policy node."""
    from runtime.nodes.camera_node import CameraNodeConfig
    from runtime.nodes.policy_node import PolicyNodeConfig
    from runtime.nodes.robot_node import RobotNodeConfig

    man = bundle_manifest(bundle)
    specs = [NodeSpec(ROBOT, "runtime.nodes.robot_node",
                      RobotNodeConfig(robot_ip=robot_ip, allow_motion=allow_motion, cameras=(), **robot_overrides))]
    for cam in man["cameras"]:
        if cam not in camera_serials:
            raise ValueError(f"the bundle needs camera {cam!r}: give its serial (--camera-serial {cam}=SERIAL)")
        specs.append(NodeSpec(f"camera_{cam}", "runtime.nodes.camera_node",
                              CameraNodeConfig(name=cam, serial=camera_serials[cam])))
    specs.append(NodeSpec("policy", "runtime.nodes.policy_node",
                          PolicyNodeConfig(bundle=str(bundle), command=command, replan_every=replan_every,
                                           speed=speed, goal_query=goal_query, phases=phases,
                                           cell_ceiling_m=_declared_ceiling(robot_overrides.get("limits_file")))))
    return specs


def _declared_ceiling(limits_file: str | None) -> float | None:
    """The highest fixture a real cell's limits file declares (runtime.free_pace.ceiling_of); None without one:
    the default limits say nothing of the cell's furniture, so the policy node keeps every family's pace."""
    if not limits_file:
        return None
    from runtime.free_pace import ceiling_of
    from safety import load_limits

    return ceiling_of(load_limits(limits_file))


def answers(event, command_id: str) -> bool:
    """Whether a StatusEvent is the policy node's answer (command_accepted/_refused) to `command_id`."""
    return event.kind.startswith("command_") and event.message.startswith(f"[{command_id}]")


def policy_stack(bundle: str, command: str = "", replan_every: int = 1, speed: str = "",
                 goal_query: bool = True, phases: bool | None = None) -> list[NodeSpec]:
    """The policy node alone: for a computer that joins the robot's bus with `--connect` (a GPU box)."""
    from runtime.nodes.policy_node import PolicyNodeConfig

    return [NodeSpec("policy", "runtime.nodes.policy_node",
                     PolicyNodeConfig(bundle=str(bundle), command=command, replan_every=replan_every, speed=speed,
                                      goal_query=goal_query, phases=phases))]


def node_kind(spec: NodeSpec) -> str:
    """robot | camera | policy: what `sudd run --nodes` selects by."""
    return "camera" if spec.name.startswith("camera_") else spec.name


class Launcher:
    def __init__(self, specs: list[NodeSpec], hub: str = HUB_DEFAULT, robot_name: str = "ur5",
                 ready_timeout_s: float = 60.0, robot_stop_timeout_s: float = 8.0, grace_s: float = 5.0,
                 connect: str | None = None, connect_timeout_s: float = 10.0):
        """`hub`: where this launcher's bus listens and its nodes connect. `connect`: join the hub of a
        launcher on another computer instead (its nodes then only dial out), e.g. the policy on a GPU box."""
        from runtime.bus_config import is_loopback, split_endpoint

        if connect is None and hub.rsplit(":", 1)[-1] == "0":
            from runtime.bus import _pick_port

            hub = _pick_port(hub)
        self.hub, self.robot_name, self.remote = connect or hub, robot_name, connect is not None
        self.connect_timeout_s = connect_timeout_s
        local = is_loopback(self.hub)
        # A hub on a network address is for nodes on other computers: they reach ours directly (Zenoh peers
        # do not relay), so ours listen on the hub's address too; joined from afar, ours just dial out.
        proto, host, _ = split_endpoint(self.hub)
        listen = () if self.remote else (f"{proto}/{host}:0",)
        self.bus_settings = BusSettings(robot=robot_name, connect=(self.hub,), listen=listen, loopback_only=local)
        self.specs = [NodeSpec(s.name, s.module, _with_bus(s.config, self.bus_settings)) for s in specs]
        self.ready_timeout_s, self.robot_stop_timeout_s, self.grace_s = ready_timeout_s, robot_stop_timeout_s, grace_s
        self._ctx = mp.get_context("spawn")
        self._q = self._ctx.Queue()
        # set when a shutdown starts, before the robot node's controlled stop: the other nodes then expect their
        # inputs to stop and say nothing of it (runtime.nodes.common.NodeContext.winding_down)
        self._winding = self._ctx.Event()
        self.procs: dict[str, mp.Process] = {}
        self.stops: dict = {}
        self.ready_info: dict[str, dict] = {}
        self.reports: dict[str, dict] = {}
        self.exit_codes: dict[str, int | None] = {}
        self.shutdown_reason: str | None = None
        self.failed: list[str] = []
        self.bus = None
        self._signal = threading.Event()
        self._old_handlers: dict = {}
        self._down = False

    # ---- start -----------------------------------------------------------------------------------------
    def start(self) -> "Launcher":
        """Open the bus (NodeFailed if `connect` finds nobody) and start every node; a second call is a no-op."""
        from runtime.bus import Bus, BusConfig

        if self.bus is not None:
            return self
        hub = (self.hub,)
        bus = Bus.open(BusConfig(robot=self.robot_name, listen=() if self.remote else hub,
                                 connect=hub if self.remote else (), loopback_only=self.bus_settings.loopback_only))
        if self.remote and not bus.wait_for_peers(1, self.connect_timeout_s):
            bus.close()
            raise NodeFailed(f"nothing answers at {self.hub}: start `sudd run ... --hub {self.hub}` on the "
                             "robot's computer first, and check the address and that the port is open")
        self.bus = bus
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old_handlers[sig] = signal.signal(sig, self._on_signal)
        from runtime.nodes.common import process_entry

        for s in self.specs:
            ev = self._ctx.Event()
            p = self._ctx.Process(target=process_entry, name=f"sudd-{s.name}",
                                  args=(s.module, config_to_dict(s.config), s.name, self._q, ev, self._winding))
            p.start()
            self.procs[s.name], self.stops[s.name] = p, ev
        return self

    def _on_signal(self, signum, frame) -> None:
        self._signal.set()
        self.shutdown_reason = self.shutdown_reason or f"signal {signal.Signals(signum).name}"

    def _drain(self, timeout: float = 0.0) -> None:
        try:
            while True:
                name, kind, payload = self._q.get(timeout=timeout) if timeout else self._q.get_nowait()
                if kind == "ready":
                    self.ready_info[name] = payload
                elif kind == "exit":
                    self.reports[name] = payload
                timeout = 0.0
        except (queue.Empty, EOFError, OSError):
            pass

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if not p.is_alive()]

    def alive(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.is_alive()]

    def wait_ready(self, timeout_s: float | None = None) -> dict:
        """Wait until every node reported ready; NodeFailed (after a full shutdown) if one dies or times out."""
        deadline = time.monotonic() + (timeout_s or self.ready_timeout_s)
        while len(self.ready_info) < len(self.procs):
            self._drain(0.05)
            gone = [n for n in self.dead() if n not in self.ready_info]
            if gone or time.monotonic() > deadline or self._signal.is_set():
                self._drain(0.2)
                why = (f"node(s) {', '.join(gone)} exited during start-up: "
                       + "; ".join(str(self.reports.get(n, {}).get("error", "no report")) for n in gone)) if gone \
                    else ("interrupted" if self._signal.is_set() else "start-up timed out")
                self.shutdown(why)
                raise NodeFailed(why)
        return self.ready_info

    # ---- run -------------------------------------------------------------------------------------------
    def say(self, text: str, command_id: str = "launch", wait_s: float = 5.0) -> None:
        """Publish a language command, after waiting up to `wait_s` for a policy node to subscribe."""
        from runtime import bus as B
        from runtime import messages as m

        pub = self.bus.publisher(B.LANGUAGE_COMMAND)
        pub.wait_matched(wait_s)
        pub.publish(m.LanguageCommand(text=text, command_id=command_id))

    def say_until_answered(self, text: str, command_id: str = "launch", every_s: float = 1.0):
        """Send `text` now and again every `every_s` until a policy node answers it (command_accepted or
        command_refused): for a policy node on another computer, which may join later. Returns a poll
        function for `monitor(until=...)`-style loops that resends when due and is True once answered."""
        from runtime import bus as B

        answered, last = threading.Event(), [time.monotonic()]
        self.bus.subscribe(B.SAFETY_EVENT, lambda e: answered.set() if answers(e, command_id) else None)
        self.say(text, command_id, wait_s=0.0)  # the monitor loop must not block on an absent node

        def poll() -> bool:
            if not answered.is_set() and time.monotonic() - last[0] >= every_s:
                last[0] = time.monotonic()
                self.say(text, command_id, wait_s=0.0)
            return answered.is_set()

        return poll

    def monitor(self, duration_s: float | None = None, until=None, poll_s: float = 0.05) -> str:
        """Watch the nodes until `duration_s`, `until()` true, a signal or a node exiting; then shut down
        (robot first). Returns the reason."""
        t_end = None if duration_s is None else time.monotonic() + duration_s
        reason = None
        while reason is None:
            self._drain(poll_s)
            gone = self.dead()
            if gone:
                self.failed += [n for n in gone if n not in self.failed]
                reason = f"node(s) {', '.join(gone)} exited (exit code " \
                         f"{', '.join(str(self.procs[n].exitcode) for n in gone)})"
            elif self._signal.is_set():
                reason = self.shutdown_reason or "signal"
            elif until is not None and until():
                reason = "condition met"
            elif t_end is not None and time.monotonic() >= t_end:
                reason = "duration over"
        self.shutdown(reason)
        return reason

    # ---- stop ------------------------------------------------------------------------------------------
    def shutdown(self, reason: str = "shutdown") -> None:
        """Robot node's controlled stop first, then the rest; nothing left running. Idempotent."""
        if self._down:
            return
        self._down = True
        self.shutdown_reason = self.shutdown_reason or reason
        t0 = time.monotonic()
        self._winding.set()
        robot = self.procs.get(ROBOT)
        if robot is not None and robot.is_alive():
            self.stops[ROBOT].set()
            robot.join(self.robot_stop_timeout_s)
        self.robot_stopped_after_s = time.monotonic() - t0
        for name, ev in self.stops.items():
            ev.set()
        deadline = time.monotonic() + self.grace_s
        for p in self.procs.values():
            p.join(max(0.0, deadline - time.monotonic()))
        for p in self.procs.values():
            if p.is_alive():
                log.warning("%s did not stop in time: terminating", p.name)
                p.terminate()
                p.join(2.0)
            if p.is_alive():
                p.kill()
                p.join(2.0)
        self._drain(0.2)
        for name, p in self.procs.items():
            self.exit_codes[name] = p.exitcode
        if self.bus is not None:
            self.bus.close()
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        self._old_handlers.clear()
        self._q.close()
        self._q.join_thread()

    def __enter__(self) -> "Launcher":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.shutdown("context exit" if exc[0] is None else f"{exc[0].__name__} in the launcher")


__all__ = ["Launcher", "NodeSpec", "NodeFailed", "sim_stack", "hardware_stack", "policy_stack", "node_kind",
           "answers", "bundle_manifest"]
