"""Runtime nodes without processes: no torch in the runtime, the bundle requirement, small helpers."""

import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.nodes.common import config_from_dict, config_to_dict
from runtime.nodes.policy_node import PolicyNodeConfig, proprio_of, resize_nearest
from runtime.nodes.robot_guards import GuardedArm, GuardedFilter
from runtime.nodes.robot_node import RobotNodeConfig


def test_runtime_never_imports_torch():
    mods = ["runtime.nodes.policy_node", "runtime.nodes.robot_node", "runtime.nodes.camera_node", "runtime.launch",
            "runtime.run_cli", "runtime.bench_runtime", "runtime.cli"]
    code = "import sys\n" + "".join(f"import {m}\n" for m in mods) + \
        "import runtime.cli as c; c.build_parser()\n" \
        "bad = [m for m in sys.modules if m == 'torch' or m.startswith('torch.')]\nassert not bad, bad[:5]\n"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_config_round_trip():
    cfg = RobotNodeConfig(task="stack", seed=3, cameras=("scene",), image_size=(96, 96))
    assert config_from_dict(RobotNodeConfig, config_to_dict(cfg)) == cfg
    p = PolicyNodeConfig(bundle="x", similarity_threshold=0.5)
    assert config_from_dict(PolicyNodeConfig, config_to_dict(p)) == p
    with pytest.raises(ValueError, match="no field"):
        config_from_dict(PolicyNodeConfig, {"nope": 1})


def test_resize_and_proprio():
    img = np.arange(480 * 640 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 640, 3)
    out = resize_nearest(img, 128, 128)
    assert out.shape == (128, 128, 3) and out.dtype == np.uint8
    assert resize_nearest(out, 128, 128) is out
    s = SimpleNamespace(tcp_pose=np.array([0.1, 0.2, 0.3, np.pi, 0, 0]), q=np.arange(6.0))
    p = proprio_of(s, 0.5)
    assert p.shape == (16,) and np.allclose(p[:3], [0.1, 0.2, 0.3]) and p[9] == 0.5
    assert np.allclose(p[3:9], [1, 0, 0, 0, -1, 0], atol=1e-9) and np.allclose(p[10:], np.arange(6.0))


def test_guarded_arm_passes_only_the_filter_output():
    sent = []
    arm = SimpleNamespace(servo_j=lambda q, *a: sent.append(q) or True)
    filt = GuardedFilter(SimpleNamespace(step=lambda *a: SimpleNamespace(q=np.ones(6)), dt=0.002))
    g = GuardedArm(arm, filt)
    assert not g.servo_j(np.ones(6))  # before any filter step: nothing may pass
    filt.step()
    assert g.servo_j(np.ones(6)) and not g.servo_j(np.zeros(6))
    assert (g.servo_sent, g.bypass, len(sent)) == (1, 2, 1) and filt.dt == 0.002


def test_run_requires_a_policy(monkeypatch, tmp_path, capsys):
    from runtime import run_cli
    from runtime.cli import main

    monkeypatch.delenv(run_cli.BUNDLE_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--sim", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "--policy" in err and "sudd train" in err and "sudd export" in err


def _manifest(d):
    import json

    man = {"cameras": ["scene"], "image_size": [96, 96], "horizons": {"action": 8}}
    (d / "manifest.json").write_text(json.dumps(man))


def test_replan_every_is_checked_against_the_bundle_and_reaches_the_policy_node(tmp_path, capsys):
    from policy.bundle import check_replan_every
    from runtime.cli import main
    from runtime.launch import policy_stack, sim_stack

    for bad in (0, 9, True, 2.0):
        with pytest.raises(ValueError, match=r"replan_every = .*1\.\.8"):
            check_replan_every(bad, 8)
    check_replan_every(8, 8)
    _manifest(tmp_path)
    assert main(["run", "--sim", "--policy", str(tmp_path), "--replan-every", "9"]) == 2
    assert "1..8" in capsys.readouterr().err
    for spec in (sim_stack(str(tmp_path), replan_every=4)[1], policy_stack(str(tmp_path), replan_every=4)[0]):
        assert config_from_dict(PolicyNodeConfig, config_to_dict(spec.config)).replan_every == 4


def test_controller_file_reaches_the_robot_node_and_bad_files_are_refused(tmp_path, capsys):
    """`sudd run --controller FILE`: a real UR needs its own servo lag (execution_latency); the file's
    fields reach the robot node's ControllerLoop on the sim and the hardware stack, a bad file stops the
    launcher before any node starts, with the field and its range."""
    from runtime.cli import main
    from runtime.controller import ControllerConfig, load_controller
    from runtime.launch import hardware_stack, sim_stack
    from sim.config import ConfigError

    _manifest(tmp_path)
    good = tmp_path / "ur5.toml"
    good.write_text("execution_latency = 0.1\ngripper_min_hold = 0.6\n")
    cfg = load_controller(good)
    assert (cfg.execution_latency, cfg.gripper_min_hold, cfg.blend_time) == (0.1, 0.6, ControllerConfig().blend_time)
    sim = sim_stack(str(tmp_path), controller=cfg)[0].config
    hw = hardware_stack(str(tmp_path), "10.0.0.2", {"scene": "123"}, controller=cfg)[0].config
    for robot in (sim, hw):
        back = config_from_dict(RobotNodeConfig, config_to_dict(robot))  # the trip to the node process
        assert back.controller == cfg
    assert RobotNodeConfig().controller == ControllerConfig()

    typo = tmp_path / "typo.toml"
    typo.write_text("gripper_hold = 0.6\n")
    with pytest.raises(ConfigError, match="gripper_min_hold"):
        load_controller(typo)
    far = tmp_path / "far.toml"
    far.write_text("execution_latency = 2.0\n")
    assert main(["run", "--sim", "--policy", str(tmp_path), "--controller", str(far)]) == 2
    err = capsys.readouterr().err
    assert "execution_latency" in err and "0.5" in err
    assert main(["run", "--policy", str(tmp_path), "--nodes", "policy", "--controller", str(good)]) == 2
    assert "--sim or --robot-ip" in capsys.readouterr().err


def test_limits_file_reaches_the_robot_node_and_bad_files_are_refused(tmp_path, capsys):
    """`sudd run --limits FILE`: the cell's workspace box and speeds (safety/limits_example.toml) are the
    ones the robot node's safety filter enforces; a limit out of range stops the launcher before any node."""
    from pathlib import Path

    from runtime.cli import main
    from runtime.launch import sim_stack
    from safety import default_limits, load_limits

    _manifest(tmp_path)
    example = Path(__file__).resolve().parents[1] / "safety" / "limits_example.toml"
    robot = sim_stack(str(tmp_path), limits_file=str(example))[0].config
    robot = config_from_dict(RobotNodeConfig, config_to_dict(robot))
    node = load_limits(robot.limits_file or None, variant="ur5e")  # what the node's filter is built from
    assert len(node.workspace.keepout) == 1 and not default_limits("ur5e").workspace.keepout
    assert node != default_limits("ur5e")
    assert load_limits(RobotNodeConfig().limits_file or None, variant="ur5e") == default_limits("ur5e")
    bad = tmp_path / "fast.toml"
    bad.write_text("[tcp]\nmax_linear_speed = 50.0\n")
    assert main(["run", "--sim", "--policy", str(tmp_path), "--limits", str(bad)]) == 2
    assert "max_linear_speed" in capsys.readouterr().err


def test_help_documents_hardware_and_say(capsys):
    from runtime.cli import main

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert "--robot-ip" in out and "--allow-motion" in out and "checklist" in out and "--camera-serial" in out
    with pytest.raises(SystemExit):
        main(["say", "--help"])
    assert "--connect" in capsys.readouterr().out


def test_sim_render_world_is_bit_identical_and_renders_the_same_image():
    """sim_render's world (its own build_episode) set from a snapshot of the robot node's physics renders
    exactly what the robot node's own world would."""
    import types as _types

    import mujoco

    from runtime.nodes.sim_render import _build, model_digest, state_spec
    from sim.render import CameraRenderer
    from sim.twins.rig import SimRig

    a, b = _build("pick_place", 0, "off", {}), _build("pick_place", 0, "off", {})
    assert model_digest(a.world.model) == model_digest(b.world.model)
    rig = SimRig(a.world, "lockstep")
    rig.arm.servo_j(np.asarray(rig.arm.state().q) + 0.05)
    rig.step(50)
    spec = state_spec()
    buf = np.empty(mujoco.mj_stateSize(a.world.model, spec))
    mujoco.mj_getState(a.world.model, a.world.data, buf, spec)
    d = mujoco.MjData(b.world.model)
    mujoco.mj_setState(b.world.model, d, buf, spec)
    mujoco.mj_forward(b.world.model, d)
    assert np.array_equal(d.qpos, a.world.data.qpos)
    ref = mujoco.MjData(a.world.model)  # as the in-process SimCamera renders a snapshot: qpos + mocap, kinematics
    src = a.world.data
    ref.qpos[:], ref.mocap_pos[:], ref.mocap_quat[:] = src.qpos, src.mocap_pos, src.mocap_quat
    mujoco.mj_kinematics(a.world.model, ref)
    mujoco.mj_camlight(a.world.model, ref)
    ra = CameraRenderer(_types.SimpleNamespace(model=a.world.model, data=ref), 64, 64, shadows=False)
    rb = CameraRenderer(_types.SimpleNamespace(model=b.world.model, data=d), 64, 64, shadows=False)
    try:
        for cam in ("scene_cam", "gripper/wrist_cam"):
            assert np.array_equal(ra.rgb(cam), rb.rgb(cam))
    finally:
        ra.close()
        rb.close()


def test_sim_run_builds_the_scene_sudd_eval_runs_for_the_same_seed(tmp_path):
    """The bundle's training data kept purple objects out, so `sudd eval`'s seed K never names a purple
    target; `sudd run --sim --seed K` must build that same scene (not the unrestricted one) in the robot node
    and in its render process."""
    import json

    from runtime.launch import sim_stack
    from runtime.nodes.robot_node import scene_holdout
    from runtime.nodes.sim_render import _build, model_digest
    from sim.build import build_episode
    from sim.tasks import Holdout

    seed = 100_002  # unrestricted, this seed's target is the purple block
    assert "purple" in build_episode("pick_place", seed, "heavy", "fast").instruction
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"cameras": ["scene", "wrist"], "image_size": [128, 128], "data": {"holdout": {"colors": ["purple"]}}}))
    robot = sim_stack(str(tmp_path), seed=seed, dr="heavy")[0].config
    assert robot.holdout_colors == ("purple",) and robot.holdout_shapes == ()
    assert config_from_dict(RobotNodeConfig, config_to_dict(robot)) == robot  # survives the trip to the node
    ours = build_episode("pick_place", seed, "heavy", "fast", holdout=scene_holdout(robot))
    evals = build_episode("pick_place", seed, "heavy", "fast", holdout=Holdout(colors=("purple",)))
    assert ours.instruction == evals.instruction and "purple" not in ours.instruction
    rendered = _build("pick_place", seed, "heavy", {"colors": ["purple"]})
    assert model_digest(rendered.world.model) == model_digest(ours.world.model)
