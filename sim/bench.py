"""Simulation benchmark: physics steps/s, renders/s per fidelity level and resolution, scene build times.

    sudd bench sim            # a readable table
    sudd bench sim --json     # the figures as JSON
    taskset -c 0 sudd bench sim --json   # one core, as datagen workers run

Every figure is the median of several repetitions taken in one run. The scene is the robot on its table with a
bin and a few blocks, built directly from sim.scene and sim.objects (no task, no domain randomization). Renders
alternate between the scene camera and the wrist camera and count one each.
"""

from __future__ import annotations

import os
import platform
import statistics
import time

import mujoco
import numpy as np

from sim import fidelity
from sim.fidelity import FIDELITY_LEVELS, apply_fidelity, render_settings
from sim.objects import Placement, add_bin, add_block, add_cylinder
from sim.render import CameraRenderer
from sim.robot import WRIST_CAMERA
from sim.scene import SCENE_CAMERA, base_scene
from sim.world import World

CAMERAS = (SCENE_CAMERA, WRIST_CAMERA)
RESOLUTIONS = {"full": ((128, 128), (320, 240)), "fast": ((128, 128), (320, 240), (640, 480))}


def bench_scene(level: str) -> mujoco.MjSpec:
    """The benchmark scene at one fidelity level, as a spec: robot, table, a bin, three blocks and a can."""
    spec = base_scene()
    add_bin(spec, "bin", (0.08, 0.10, 0.03), (0.25, 0.45, 0.7, 1.0), Placement(0.22, 0.52))
    blocks = ((-0.15, (0.85, 0.2, 0.15, 1)), (-0.05, (0.2, 0.7, 0.25, 1)), (0.05, (0.9, 0.8, 0.1, 1)))
    for i, (x, rgba) in enumerate(blocks):
        add_block(spec, f"block{i}", (0.02, 0.02, 0.02), rgba, Placement(x, 0.42, yaw=0.3 * i))
    add_cylinder(spec, "can", 0.025, 0.04, (0.6, 0.6, 0.65, 1), Placement(-0.2, 0.6))
    apply_fidelity(spec, level)
    return spec


def _median(values) -> float:
    return float(statistics.median(values))


def _visible_mesh_vertices(model: mujoco.MjModel) -> int:
    """Vertices of the meshes drawn by default (geom groups 0-2), each mesh counted once."""
    meshes = {int(model.geom_dataid[g]) for g in range(model.ngeom)
              if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] <= 2}
    return int(sum(model.mesh_vertnum[m] for m in meshes))


def _build_times(level: str, reps: int) -> dict:
    """Spec build (scene + objects + fidelity) and compile, cold (empty asset cache) and warm, in seconds."""
    def one():
        t0 = time.perf_counter()
        spec = bench_scene(level)
        t1 = time.perf_counter()
        spec.compile()
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1

    cold = []
    for _ in range(reps):
        mujoco.mj_clearCache(mujoco.mj_getCache())
        fidelity._INERTIA_CACHE.clear()  # what a fresh process has
        cold.append(one())
    warm = [one() for _ in range(reps)]
    return {
        "spec_s": _median([w[0] for w in warm]),
        "compile_cold_s": _median([c[1] for c in cold]),
        "compile_warm_s": _median([w[1] for w in warm]),
        "total_cold_s": _median([sum(c) for c in cold]),
        "total_warm_s": _median([sum(w) for w in warm]),
    }


def _physics(world: World, steps: int, reps: int) -> dict:
    """Steps/s with the arm holding its home pose (servo targets = home), gripper open, objects at rest."""
    world.reset()
    world.set_gripper(0.0)
    world.step(200)  # settle the objects and the servo
    rates = []
    for _ in range(reps):
        t0 = time.perf_counter()
        world.step(steps)
        rates.append(steps / (time.perf_counter() - t0))
    rate = _median(rates)
    return {"steps_per_s": rate, "realtime_factor": rate * world.timestep, "timestep_s": world.timestep,
            "ncon_at_rest": int(world.data.ncon)}


def _renders(world: World, width: int, height: int, per_rep: int, reps: int,
             shadows: bool | None = None) -> tuple[float, float]:
    """(renders/s, renderer setup seconds) alternating the two cameras; shadows default to the level's."""
    t0 = time.perf_counter()
    renderer = CameraRenderer(world, width, height, shadows=shadows)
    setup = time.perf_counter() - t0
    try:
        renderer.rgb(CAMERAS[0])  # warm-up: the first draw compiles shaders and uploads textures
        if _GL_INFO.get("renderer") is None:
            _GL_INFO["renderer"] = _gl_string()
        rates = []
        for _ in range(reps):
            t0 = time.perf_counter()
            for i in range(per_rep):
                renderer.rgb(CAMERAS[i % len(CAMERAS)])
            rates.append(per_rep / (time.perf_counter() - t0))
        return _median(rates), setup
    finally:
        renderer.close()


_GL_INFO: dict = {}


def _gl_string() -> str | None:
    """GL_RENDERER of the current context (e.g. llvmpipe), informative only."""
    try:
        from OpenGL import GL

        value = GL.glGetString(GL.GL_RENDERER)
        return value.decode() if isinstance(value, bytes) else value
    except Exception:
        return None


def _machine() -> dict:
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        affinity = os.cpu_count()
    return {
        "cpu_count": os.cpu_count(),
        "cpu_affinity": affinity,
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "lp_num_threads": os.environ.get("LP_NUM_THREADS"),
        "mujoco": mujoco.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
    }


def run_sim_bench(quick: bool = False) -> dict:
    """Measure everything once and return the figures as a JSON-able dict (medians; seconds and rates)."""
    t_start = time.perf_counter()
    build_reps = 1 if quick else 3
    phys_steps, phys_reps = (250, 3) if quick else (1000, 7)
    result: dict = {"quick": quick, "machine": _machine(), "scene": {}, "build": {}, "renders_per_s": {},
                    "render_setup_s": {}, "render_settings": {}}

    # Builds first, so that `cold` really starts from an empty asset cache.
    for level in FIDELITY_LEVELS:
        result["build"][level] = _build_times(level, build_reps)

    worlds = {}
    for level in FIDELITY_LEVELS:
        model = bench_scene(level).compile()
        worlds[level] = World(model)
        result["scene"][level] = {"ngeom": int(model.ngeom), "nbody": int(model.nbody),
                                  "mesh_vertices_model": int(model.nmeshvert),
                                  "mesh_vertices_drawn": _visible_mesh_vertices(model)}
        settings = render_settings(level)
        result["render_settings"][level] = {
            "shadows": settings.shadows, "offsamples": int(model.vis.quality.offsamples),
            "shadowsize": int(model.vis.quality.shadowsize), "numslices": int(model.vis.quality.numslices)}

    # Physics is the same at both levels (only visual geoms differ); measure it on the fast model.
    result["physics"] = _physics(worlds["fast"], phys_steps, phys_reps)

    for level in FIDELITY_LEVELS:
        world = worlds[level]
        world.reset()
        result["renders_per_s"][level] = {}
        result["render_setup_s"][level] = {}
        for width, height in RESOLUTIONS[level]:
            if level == "full":  # shadow maps make these ~0.4 s each on a software renderer
                per_rep, reps = (2, 1) if quick else (4, 3)
            else:
                per_rep, reps = (10, 3) if quick else (40, 5)
            rate, setup = _renders(world, width, height, per_rep, reps)
            key = f"{width}x{height}"
            result["renders_per_s"][level][key] = rate
            result["render_setup_s"][level][key] = setup

    # What the levels' render settings are worth on their own, at the smallest size: the full meshes without
    # shadows, and the fast robot with shadows turned back on.
    per_rep, reps = (6, 1) if quick else (20, 3)
    result["renders_per_s_variants"] = {
        "full_no_shadows": {"128x128": _renders(worlds["full"], 128, 128, per_rep, reps, shadows=False)[0]},
        "fast_with_shadows": {"128x128": _renders(worlds["fast"], 128, 128, per_rep, reps, shadows=True)[0]},
    }

    result["episode_build_s"] = _episode_builds(reps=2 if quick else 5)

    result["machine"]["gl_renderer"] = _GL_INFO.get("renderer")
    full, fast = result["renders_per_s"]["full"], result["renders_per_s"]["fast"]
    result["fast_over_full"] = {key: fast[key] / full[key] for key in full if key in fast}
    result["bench_s"] = time.perf_counter() - t_start
    return result


def _episode_builds(reps: int) -> dict:
    """Median time to sample a task, build its scene, randomize it (heavy DR), compile and settle it."""
    from sim.build import build_episode

    out = {}
    for task in ("pick_place", "drawer_put"):
        for level in FIDELITY_LEVELS:
            times = []
            for seed in range(reps):
                t0 = time.perf_counter()
                build_episode(task, seed, "heavy", level, settle=False)
                times.append(time.perf_counter() - t0)
            out[f"{task}/{level}/heavy"] = _median(times)
    return out


def format_table(result: dict) -> str:
    m = result["machine"]
    lines = [f"sim bench{' (quick)' if result['quick'] else ''}: {m['cpu_affinity']}/{m['cpu_count']} CPUs, "
             f"MUJOCO_GL={m['mujoco_gl']}, GL={m.get('gl_renderer')}, MuJoCo {m['mujoco']}", ""]
    p = result["physics"]
    lines.append(f"physics        {p['steps_per_s']:10.0f} steps/s   ({p['realtime_factor']:.1f}x real time, "
                 f"dt {p['timestep_s'] * 1e3:g} ms)")
    lines.append("")
    lines.append(f"{'renders/s':14} " + " ".join(f"{k:>10}" for k in ("128x128", "320x240", "640x480")))
    for level, rates in result["renders_per_s"].items():
        cells = [f"{rates[k]:10.1f}" if k in rates else f"{'-':>10}" for k in ("128x128", "320x240", "640x480")]
        lines.append(f"{level:14} " + " ".join(cells))
    ratio = result["fast_over_full"]
    lines.append(f"{'fast/full':14} " + " ".join(f"{ratio[k]:9.1f}x" if k in ratio else f"{'-':>10}"
                                                for k in ("128x128", "320x240", "640x480")))
    for name, rates in result["renders_per_s_variants"].items():
        lines.append(f"{name:18} {rates['128x128']:6.1f}")
    lines.append("")
    lines.append(f"{'build (s)':14} {'spec':>8} {'compile':>8} {'cold':>8} {'warm':>8}"
                 "   (spec + compile; cold = empty asset cache)")
    for level, b in result["build"].items():
        lines.append(f"{level:14} {b['spec_s']:8.3f} {b['compile_warm_s']:8.3f} {b['total_cold_s']:8.3f} "
                     f"{b['total_warm_s']:8.3f}")
    for key, seconds in result.get("episode_build_s", {}).items():
        lines.append(f"episode {key:28} {seconds:8.3f} s   (sample task + build + DR + compile)")
    lines.append("")
    for level, s in result["scene"].items():
        rs = result["render_settings"][level]
        lines.append(f"{level:14} {s['ngeom']} geoms, {s['mesh_vertices_drawn']} mesh vertices drawn; shadows "
                     f"{'on' if rs['shadows'] else 'off'}, {rs['offsamples']}x MSAA")
    lines.append(f"\ntook {result['bench_s']:.1f} s")
    return "\n".join(lines)
