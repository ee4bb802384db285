"""Why a closed-loop episode failed: what the gripper held along the way, read from the sim at every tick.

A success rate says how often; this says where a policy goes wrong, which is what decides the next
experiment (more data? better grounding? finer placing?). The classes, in the order a pick-and-place
episode could reach them:

    no_grasp          the gripper never held any object ("held": both finger pads on it and the object lifted at
                      least LIFT_M off where it started, so fingertips resting on a bar's top do not count)
    wrong_object      it held an object, never the one the command named
    target_not_placed it held the named object, but the episode ended without the task's success
                      (dropped on the way, released outside the goal, or stopped while carrying it)

An episode that ends in a protective stop also keeps its stop as `end`, so the two read together:
"protective_stop + wrong_object". Tasks without a named object (open a drawer) report only no_grasp.

A target_not_placed episode also says where the named object was at the end (`target_end`): still "held",
in a "wrong_bin", in the "goal" but not settled there, or "outside" every container (dropped on the way or let
go beside its bin); "released" for a task without bins (stack, drawer_put); and `target_lets_go` counts the
times the gripper stopped holding it (one for a clean place).

`closest_m` grades a no_grasp: how near the TCP came to the named object before it first held it. A blind
policy that drives to the average target stays 10-20 cm away; one that sees closes to within a few cm and
misses by a finger's width. Success rates of 0 % cannot tell those apart.

`drawer_max` and `drawer_end` grade a task with the cabinet's drawer (drawer_open, drawer_close, drawer_put):
the most it was open at any tick and at the end, as fractions of its travel. drawer_put has four stages (open,
pick, place inside, close); these with `held` say which one an episode reached.

`closes` says how each close of the fingers before the named object was held missed it: the TCP's
horizontal offset from the object, its height over the object's centre (`up_cm`: a close square over a
cylinder's middle that holds nothing was made too high or too low), and its yaw off the object's grasp yaw,
modulo the turn that maps the object's footprint onto itself (a half turn for a bar, a quarter for a square
block; none for a cylinder, whose yaw is None). A bar closed along its length is missed however near the TCP
comes.

`releases` says where the named object was each time the fingers stopped holding it, for a task with a goal
bin, the drawer's inside (drawer_put, drawer_stow) or, for stack, the block to put it on: its offset from the
goal's centre (x, y, in the world frame), the TCP's, its height over where it started and its horizontal speed;
for stack also `over_cm`, how high over resting on the other block it was let go (a block dropped from 3 cm tips
off one it lands 2 cm off); for the drawer `outside_cm`, how far beyond the inside's edges (0: over it). A place
that misses by a few centimetres beside the bin reads apart from a drop on the way (tens of centimetres), from a
release too high and from one made while still moving; the sign of the offsets shows a bias to one side, and the
TCP's whether the arm arrived off or the object hung off the TCP. With the plan the controller follows (`plan`:
the newest accepted chunk), `aim_dx_cm` and `aim_dy_cm` say where that chunk wanted the TCP at the moment of the
let-go: an aim off the centre is the policy's error, a TCP off an aim on the centre the controller's.
"""

from __future__ import annotations

import numpy as np

from sim.state import StateView
from sim.tasks.drawer import CABINET, drawer_fraction
from sim.tasks.pick_place import footprint_period, grasp_yaw

FAILURES = ("no_grasp", "wrong_object", "target_not_placed")
TARGET_ENDS = ("held", "outside", "wrong_bin", "goal", "released")
LIFT_M = 0.01
CABINET_PARAM = "cabinet"  # a task instance with this parameter has the drawer
DRAWER_INSIDE = f"{CABINET}/inside"  # the drawer's cavity, a box site that slides with it
STACK_BASE = "bottom"  # stack's goal: the object the named one goes on


def target_name(inst) -> str | None:
    """The object the command names (pick_place, drawer_put: target; stack: the one to put on top)."""
    return inst.params.get("target") or inst.params.get("top")


class GraspProgress:
    """An observer for `run_policy_episode`: call it with (world, instance) at every policy tick."""

    def __init__(self):
        self.held: list[str] = []  # objects held at some tick, in the order first held
        self.target: str | None = None
        self.closest_m: float | None = None  # TCP to the named object, while the gripper had not yet held it
        self.target_lets_go = 0  # times the named object went from held to not held
        self._holding_target = False
        self._view = None
        self._start_z: dict[str, float] = {}
        self.closes: list[dict] = []  # {"off_cm", "yaw_off_deg"} at each close before the named object was held
        self.releases: list[dict] = []  # {"dx_cm", "dy_cm", "tcp_dx_cm", ...} at each let-go of the named object
        self._closing = False
        self._held_at: np.ndarray | None = None  # the named object's position at the last tick it was held
        self._plan: tuple[np.ndarray, np.ndarray] | None = None  # the accepted chunk: times (s), positions (m)
        self.drawer_max: float | None = None  # the drawer's largest open fraction so far (None: no drawer)
        self.drawer_end: float | None = None  # and its latest

    def plan(self, times_s, positions) -> None:
        """The chunk the controller now follows: its action times (s, the sim's clock) and TCP targets (N, 3)."""
        self._plan = np.asarray(times_s, float), np.asarray(positions, float)

    def __call__(self, world, inst) -> None:
        if self._view is None:
            self._view = StateView(world)
            self.target = target_name(inst)
            self._start_z = {o.name: float(self._view.position(o.name)[2]) for o in inst.objects}
        for o in inst.objects:
            holding = self._holds(o.name)
            if o.name not in self.held and holding:
                self.held.append(o.name)
            if o.name == self.target:
                if self._holding_target and not holding:
                    self.target_lets_go += 1
                    self._release(world, inst)
                self._holding_target = holding
                if holding:
                    self._held_at = self._view.position(o.name).copy()
        if CABINET_PARAM in inst.params:
            self.drawer_end = float(drawer_fraction(self._view))
            self.drawer_max = max(self.drawer_end, self.drawer_max or 0.0)
        closing = world.gripper_command() > 0.5
        if self.target is not None and self.target not in self.held:
            d = float(np.linalg.norm(world.tcp_pose()[:3, 3] - self._view.position(self.target)))
            self.closest_m = d if self.closest_m is None else min(self.closest_m, d)
            if closing and not self._closing:
                self.closes.append(self._miss(world, inst))
        self._closing = closing

    def _miss(self, world, inst) -> dict:
        T = world.tcp_pose()
        obj = inst.obj(self.target)
        at = self._view.position(self.target)
        miss = {"off_cm": round(100 * float(np.linalg.norm(T[:2, 3] - at[:2])), 1),
                "up_cm": round(100 * float(T[2, 3] - at[2]), 1), "yaw_off_deg": None}
        period = footprint_period(obj)
        if period is not None:
            off = (float(np.arctan2(T[1, 0], T[0, 0])) - grasp_yaw(obj, self._view.rotation(self.target))
                   + period / 2) % period - period / 2
            miss["yaw_off_deg"] = round(float(np.degrees(off)), 1)
        return miss

    def _release(self, world, inst) -> None:
        goal = inst.params.get("bin") or inst.params.get(STACK_BASE)
        at, over = self._view.position(self.target), {}
        if goal:
            centre = self._view.position(goal)[:2]
        elif CABINET_PARAM in inst.params:  # the drawer's inside wherever it has slid to, as a world-aligned box:
            # the box the success check (StateView.inside) reads
            lo, hi = self._view.aabb(DRAWER_INSIDE)
            centre = (lo[:2] + hi[:2]) / 2.0
            short = np.maximum(np.maximum(lo[:2] - at[:2], at[:2] - hi[:2]), 0.0)
            over = {"outside_cm": round(100 * float(np.linalg.norm(short)), 1)}
        else:
            return
        if goal and goal == inst.params.get(STACK_BASE):  # stack: how high over resting on the other it was let go,
            # read at the last tick it was held (a block let go 3 cm up has fallen by the next tick, 0.1 s on)
            rest = self._view.position(goal)[2] + inst.obj(goal).half_height + inst.obj(self.target).half_height
            over = {"over_cm": round(100 * float(self._held_at[2] - rest), 1)}
        dx, dy = (at[:2] - centre) * 100
        tcp_dx, tcp_dy = (world.tcp_pose()[:2, 3] - centre) * 100
        aim_dx = aim_dy = None
        if self._plan is not None:  # the chunk's target now, between its knots (held at its ends)
            times, at_knots = self._plan
            aim = np.array([np.interp(world.time, times, at_knots[:, i]) for i in (0, 1)])
            aim_dx, aim_dy = (round(float(v), 1) for v in (aim - centre) * 100)
        self.releases.append({"dx_cm": round(float(dx), 1), "dy_cm": round(float(dy), 1),
                              "tcp_dx_cm": round(float(tcp_dx), 1), "tcp_dy_cm": round(float(tcp_dy), 1),
                              "aim_dx_cm": aim_dx, "aim_dy_cm": aim_dy,
                              "up_cm": round(100 * float(at[2] - self._start_z[self.target]), 1),
                              "speed_cm_s": round(100 * float(np.hypot(*self._view.velocity(self.target)[:2])), 1),
                              **over})

    def _holds(self, name: str) -> bool:
        return bool(self._view.holding(name) and self._view.position(name)[2] - self._start_z[name] >= LIFT_M)

    def failure(self, success: bool) -> str:
        """One of FAILURES, or "" for a success."""
        if success:
            return ""
        if not self.held:
            return "no_grasp"
        if self.target is not None and self.target not in self.held:
            return "wrong_object"
        return "target_not_placed"

    def target_end(self, inst) -> str:
        """Where the named object is now, one of TARGET_ENDS; "" for a task without one or one never held."""
        if self.target is None or self.target not in self.held:
            return ""
        view = self._view  # set by the first call, which came before any object could be held
        if self._holds(self.target):
            return "held"
        goal = inst.params.get("bin")
        bins = [f"bin_{name}" for name, _ in inst.params.get("bins", [])]
        if not goal and CABINET_PARAM in inst.params:  # drawer_put: the drawer is the goal (a shut one too)
            return "goal" if view.inside(self.target, CABINET) else "outside"
        if not goal:
            return "released"
        if view.inside(self.target, goal):
            return "goal"
        return "wrong_bin" if any(view.inside(self.target, b) for b in bins if b != goal) else "outside"
