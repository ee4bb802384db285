"""safety.bench (quick smoke run), the lightness of `import safety`, the dependency rule, gripper limits."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ALLOWED = {"numpy", "mujoco", "sim.robot", "sim.kinematics", "sim.rotations", "sim.config", "sim.scene", "safety"}


def test_import_safety_is_light():
    code = ("import sys, safety; from safety import SafetyFilter, SafetyEvent, default_limits, load_limits; "
            "print('mujoco' in sys.modules, 'sim.robot' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"]


def test_safety_imports_only_what_the_dependency_rule_allows():
    for path in sorted((ROOT / "safety").glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                if top in sys.stdlib_module_names:
                    continue
                assert any(name == a or name.startswith(a + ".") for a in ALLOWED), (path.name, name)
                if name == "sim.scene":
                    assert path.name == "collision.py"
                if top == "mujoco":
                    assert path.name in ("collision.py",), (path.name, "mujoco outside the collision guard")


def test_quick_bench_reports_the_figures():
    from safety import run_safety_bench

    figures = run_safety_bench(quick=True)
    json.dumps(figures)
    for section in ("chain", "chain_limited", "collision"):
        for key in ("p50_us", "p99_us", "cycles"):
            assert figures[section][key] > 0
    assert figures["chain"]["pass_fraction"] > 0.99  # the realistic stream passes unchanged
    assert 0 < figures["chain"]["p99_cycle_fraction"] < 1
    assert set(figures["meets_targets"]) == {"chain", "chain_adversarial", "collision"}
    cell = figures["chain_cell"]
    assert cell["boxes"] == 15 and cell["pass_fraction"] > 0.99 and cell["over_chain_p50"] > 0
    adv = figures["chain_adversarial"]
    assert adv["runs"] >= 2 and len(adv["per_run"]) == adv["runs"]
    assert 0 < adv["cpu_p50_us"] <= adv["cpu_p99_us"] <= adv["cpu_max_us"] <= adv["cpu_max_us_worst_run"]
    assert 0 < adv["cpu_p99_cycle_fraction"] < 1


def test_gripper_commands_are_clamped():
    from safety.events import EventCoalescer
    from safety.gripper import limit_gripper
    from safety.limits import default_limits

    lim = default_limits()
    ev = EventCoalescer()
    cmd, changed = limit_gripper(lim, 0.05, 1.0, 500.0, 0.0, ev)
    assert cmd == (0.05, lim.gripper.max_speed, lim.gripper.max_force) and len(changed) == 2
    cmd, _ = limit_gripper(lim, 0.04, float("nan"), 20.0)
    assert cmd.speed == 0.0
    assert limit_gripper(lim, float("inf"), 0.1, 20.0)[0] is None
    assert [e.kind for e in ev.flush(0.0)] == ["gripper_speed", "gripper_force"]


@pytest.mark.parametrize("variant", ["ur5e", "ur5"])
def test_filter_runs_at_each_variant_rate(variant):
    from safety import SafetyFilter, default_limits

    f = SafetyFilter(default_limits(variant), collision=False)
    assert f.dt == pytest.approx(0.002 if variant == "ur5e" else 0.008)


def test_the_bench_cell_bins_lie_just_under_the_stream():
    """chain_cell measures the cost of a bin near the gripper: along the whole realistic stream the nearest of
    its boxes is the nearest limit of the workspace (before the table and the box), never hit, 4 cm at the
    closest."""
    from safety.bench import BENCH_BINS, realistic_stream
    from safety.fastfk import FastKinematics
    from safety.limits import load_limits
    from safety.workspace import Workspace, _hull_separation
    from sim.robot import TCP_OFFSET_Z, get_variant

    fk = FastKinematics(get_variant("ur5e"), TCP_OFFSET_Z)
    ws = Workspace(load_limits(None, "ur5e", {"workspace.keepout": BENCH_BINS}).workspace, fk)
    gaps = []
    for q in realistic_stream(20000)[::50]:
        px, py, pz, R = fk.pose(q.tolist())
        pts = ws.points((px, py, pz), R)
        gaps.append(min(_hull_separation(b, pts) for b in ws.keepout))
        assert ws.min_slack(pts) == gaps[-1]  # the bin is the nearest limit
    assert 0.03 < min(gaps) < 0.05
