"""runtime.eval_progress on hand-made states: failure classes, when a held object counts as held, each close's
miss (offset, height, yaw modulo the footprint's symmetry)."""

import numpy as np
import pytest


def test_failure_classes():
    from runtime.eval_progress import GraspProgress

    p = GraspProgress()
    p.target = "obj0"
    assert p.failure(True) == "" and p.failure(False) == "no_grasp"
    p.held = ["obj2"]
    assert p.failure(False) == "wrong_object"
    p.held = ["obj2", "obj0"]
    assert p.failure(False) == "target_not_placed"
    p.target = None  # a task that names no object (open the drawer): holding something is not "wrong"
    assert p.failure(False) == "target_not_placed"


def test_pads_on_an_object_hold_it_only_once_it_is_lifted(monkeypatch):
    from types import SimpleNamespace

    from runtime import eval_progress
    from runtime.eval_progress import LIFT_M, GraspProgress

    z = {"obj0": 0.02, "obj1": 0.02}
    bin_at = {"bin_left": np.array([0.16, 0.64, 0.0]), "bin_right": np.array([-0.16, 0.64, 0.0])}
    view = SimpleNamespace(holding=lambda name: name == "obj0", velocity=lambda name: np.array([0.03, -0.04, -0.2]),
                           position=lambda name: bin_at[name] if name in bin_at else np.array([0.0, 0.5, z[name]]))
    world = SimpleNamespace(tcp_pose=lambda: np.eye(4), gripper_command=lambda: 0.0)
    bins = {"target": "obj0", "bin": "bin_left", "bins": [["left", 0.16], ["right", -0.16]]}
    inst = SimpleNamespace(params=bins, objects=[SimpleNamespace(name=n) for n in z])
    monkeypatch.setattr(eval_progress, "StateView", lambda w: view)
    p = GraspProgress()
    p(world, inst)  # fingertips on the bar's top, both pads touching: not a grasp
    assert p.held == [] and p.failure(False) == "no_grasp"
    z["obj0"] += LIFT_M + 0.005
    p(world, inst)
    assert p.held == ["obj0"] and p.failure(False) == "target_not_placed" and p.target_end(inst) == "held"
    view.holding = lambda name: False
    view.inside = lambda obj, container: False
    p(world, inst)
    assert p.target_lets_go == 1 and p.target_end(inst) == "outside"
    # where it left the fingers, off bin_left, and how fast it went sideways then
    assert p.releases == [{"dx_cm": -16.0, "dy_cm": -14.0, "tcp_dx_cm": -16.0, "tcp_dy_cm": -64.0, "aim_dx_cm": None,
                           "aim_dy_cm": None, "up_cm": 1.5, "speed_cm_s": 5.0}]  # the TCP (at the origin) is off too
    # with a plan, where it aimed at the let-go: between the knots around the world's time
    p.plan([1.0, 2.0], [[0.16, 0.60, 0.1], [0.20, 0.70, 0.1]])
    view.holding = lambda name: True
    p(world, inst)
    view.holding = lambda name: False
    world.time = 1.5
    p(world, inst)
    assert p.target_lets_go == 2 and (p.releases[1]["aim_dx_cm"], p.releases[1]["aim_dy_cm"]) == (2.0, 1.0)
    view.inside = lambda obj, container: container == "bin_right"
    assert p.target_end(inst) == "wrong_bin"
    assert p.target_end(SimpleNamespace(params={"target": "obj0"})) == "released"  # a task without bins
    drawer_put = SimpleNamespace(params={"target": "obj0", "cabinet": {}})  # its goal is the drawer
    view.inside = lambda obj, container: container == "cabinet"
    assert p.target_end(drawer_put) == "goal"
    view.inside = lambda obj, container: False
    assert p.target_end(drawer_put) == "outside"


def test_each_close_before_the_grasp_says_how_far_off_and_how_turned_it_was(monkeypatch):
    from types import SimpleNamespace

    from runtime import eval_progress
    from runtime.eval_progress import GraspProgress
    from sim.tasks.pick_place import footprint_period

    lifted = {"obj0": False}
    view = SimpleNamespace(holding=lambda name: lifted[name], rotation=lambda name: np.eye(3),  # a bar along x
                           position=lambda name: np.array([0.0, 0.5, 0.02 + 0.05 * lifted[name]]))
    cmd, yaw = [0.0], [0.0]

    def tcp():
        T = np.eye(4)
        c, s = np.cos(yaw[0]), np.sin(yaw[0])
        T[:2, :2], T[:3, 3] = [[c, -s], [s, c]], [0.03, 0.5, 0.05]
        return T

    world = SimpleNamespace(tcp_pose=tcp, gripper_command=lambda: cmd[0])
    bar = SimpleNamespace(name="obj0", shape="bar", size=(0.045, 0.018, 0.018))
    inst = SimpleNamespace(params={"target": "obj0"}, objects=[bar], obj=lambda name: bar)
    monkeypatch.setattr(eval_progress, "StateView", lambda w: view)
    p = GraspProgress()
    for c, y in ((0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (0.0, 0.0), (1.0, np.radians(80.0))):
        cmd[0], yaw[0] = c, y
        p(world, inst)
    # closed along the bar (90 degrees off its grasp yaw, across it), then 10 degrees short of across
    assert p.closes == [{"off_cm": 3.0, "up_cm": 3.0, "yaw_off_deg": -90.0},
                        {"off_cm": 3.0, "up_cm": 3.0, "yaw_off_deg": -10.0}]
    lifted["obj0"] = True
    for c in (0.0, 1.0):  # once the named object is held, a close is no miss
        cmd[0] = c
        p(world, inst)
    assert len(p.closes) == 2 and p.held == ["obj0"]
    # a square block looks the same a quarter turn on, a cylinder at any yaw
    block = SimpleNamespace(shape="block", size=(0.022, 0.022, 0.022))
    assert footprint_period(block) == pytest.approx(np.pi / 2) and footprint_period(bar) == pytest.approx(np.pi)
    assert footprint_period(SimpleNamespace(shape="cylinder", size=(0.022, 0.024))) is None
