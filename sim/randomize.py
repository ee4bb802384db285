"""Domain randomization as pure functions of (spec, config, rng), applied to the scene spec before compile.

Why on the spec: a compiled MjModel is then an ordinary model (textures baked, lights counted, inertias
recomputed from scaled masses), and the same seed gives a bit-identical model and first frame. Each block
below says whether it SETS, SCALES or ADDS; it reads the nominal value from the spec itself, so it jitters
around whatever the scene/task built. A block whose config is the identity draws nothing and touches
nothing, so preset "off" leaves the spec exactly as it was. Each block draws from its own child of the
stream it is given (`rng.spawn`), so changing one block's range never shifts another block's samples.

`randomize_spec` returns a JSON-able record of every sampled value, for the episode record.
Object colours are not here: tasks sample them (`sim.colors.sample_rgba`, cfg.visual.object_color_spread).
"""

from __future__ import annotations

import colorsys
from dataclasses import asdict, dataclass

import mujoco
import numpy as np

from sim.dr_config import DRConfig, SensorDR, VisualDR, load_dr
from sim.robot import ARM_ACTUATORS, ARM_JOINTS, WRIST_CAMERA
from sim.scene import SCENE_CAMERA, SURFACES, add_light
from sim.seeding import EpisodeRngs, episode_rngs

_BUILTINS = {"checker": mujoco.mjtBuiltin.mjBUILTIN_CHECKER, "gradient": mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
             "flat": mujoco.mjtBuiltin.mjBUILTIN_FLAT}
_MARKS = {"none": mujoco.mjtMark.mjMARK_NONE, "edge": mujoco.mjtMark.mjMARK_EDGE,
          "cross": mujoco.mjtMark.mjMARK_CROSS, "random": mujoco.mjtMark.mjMARK_RANDOM}
# Where lights beyond the scene's own go (position, nominal diffuse): above and around the task area.
_EXTRA_LIGHTS = (((0.0, 0.5, 2.2), 0.35), ((-0.7, 1.3, 1.4), 0.3), ((0.9, -0.3, 1.3), 0.3), ((0.0, 1.6, 1.8), 0.3))
_LIGHT_MIN_Z = 0.6  # keep jittered lights above the robot's workspace, never under the table


def _f(x) -> list[float] | float:
    """Plain Python floats for the JSON record."""
    arr = np.asarray(x, dtype=float)
    return float(arr) if arr.ndim == 0 else [float(v) for v in arr.ravel()]


# -- visual ------------------------------------------------------------------------------------------
def _textures_active(v: VisualDR) -> bool:
    return v.retexture or v.surface_value != (1.0, 1.0) or v.surface_hue_jitter != 0.0


def _shift(rgb, hue_shift: float, value_scale: float) -> list[float]:
    h, s, val = colorsys.rgb_to_hsv(*np.clip(np.asarray(rgb, float)[:3], 0.0, 1.0))
    return list(colorsys.hsv_to_rgb((h + hue_shift) % 1.0, s, min(val * value_scale, 1.0)))


def _retexture(spec: mujoco.MjSpec, v: VisualDR, rng: np.random.Generator) -> dict:
    """SETS table/floor/wall textures (heavy: new builtin pattern and colours), then shifts hue and SCALES
    brightness. Colours stay muted (saturation <= ~0.65) so the scene still reads as a table in a room."""
    out = {}
    for surface in SURFACES:
        tex = spec.texture(f"{surface}_tex")
        mat = spec.material(f"{surface}_mat")
        if tex is None:
            continue
        rec: dict = {}
        rgb1, rgb2 = np.array(tex.rgb1, float), np.array(tex.rgb2, float)
        if v.retexture:
            builtin = str(rng.choice(list(_BUILTINS)))
            h, s, val = rng.uniform(0, 1), rng.uniform(0.0, 0.55), rng.uniform(0.25, 0.8)
            rgb1 = np.array(colorsys.hsv_to_rgb(h, s, val))
            h2 = (h + rng.uniform(-0.08, 0.08)) % 1.0
            val2 = float(np.clip(val + rng.choice([-1, 1]) * rng.uniform(0.1, 0.4), 0.05, 1.0))
            rgb2 = np.array(colorsys.hsv_to_rgb(h2, s * rng.uniform(0.5, 1.2), val2))
            mark = str(rng.choice(list(_MARKS)))
            markrgb = np.array(colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.0, 0.6), rng.uniform(0.1, 0.9)))
            noise = float(rng.uniform(0.005, 0.05)) if mark == "random" else 0.0
            # A gradient repeated many times reads as polka dots; keep it to one or two blobs per face.
            repeat = int(rng.integers(1, 3)) if builtin == "gradient" else int(rng.integers(1, 9))
            tex.builtin, tex.mark, tex.markrgb = _BUILTINS[builtin], _MARKS[mark], markrgb.tolist()
            if mark == "random":
                tex.random = noise
            if mat is not None:
                mat.texrepeat = [repeat, repeat]
            rec.update(builtin=builtin, mark=mark, markrgb=_f(markrgb), random=noise, texrepeat=repeat)
        hue_shift = float(rng.uniform(-v.surface_hue_jitter, v.surface_hue_jitter))
        value_scale = float(rng.uniform(*v.surface_value))
        tex.rgb1, tex.rgb2 = _shift(rgb1, hue_shift, value_scale), _shift(rgb2, hue_shift, value_scale)
        rec.update(hue_shift=hue_shift, value_scale=value_scale, rgb1=_f(tex.rgb1), rgb2=_f(tex.rgb2))
        out[surface] = rec
    return out


def _lights_active(v: VisualDR) -> bool:
    d = VisualDR()
    return (v.light_count != d.light_count or v.light_intensity != (1.0, 1.0) or v.light_pos_jitter != 0.0
            or v.shadow_probability != 1.0)


def _relight(spec: mujoco.MjSpec, v: VisualDR, rng: np.random.Generator) -> list[dict]:
    """SETS the light rig: deletes lights named light*, adds N (uniform in light_count) around the old ones
    (extra ones at fixed spots) with ADDED position jitter and SCALED diffuse. The nominal intensities are
    renormalized to the old rig's total, so the count changes light direction and shadows, not exposure."""
    old = [(np.array(lt.pos, float), float(lt.diffuse[0])) for lt in spec.lights if lt.name.startswith("light")]
    for lt in [lt for lt in spec.lights if lt.name.startswith("light")]:
        spec.delete(lt)
    bases = old + [(np.array(p, float), i) for p, i in _EXTRA_LIGHTS]
    n = int(rng.integers(v.light_count[0], v.light_count[1] + 1))
    chosen = [bases[i % len(bases)] for i in range(n)]
    total_old = sum(i for _, i in old) or sum(i for _, i in chosen)
    norm = total_old / sum(i for _, i in chosen)
    out = []
    for k, (pos, nominal) in enumerate(chosen):
        p = pos + rng.uniform(-v.light_pos_jitter, v.light_pos_jitter, 3)
        p[2] = max(p[2], _LIGHT_MIN_Z)
        scale = float(rng.uniform(*v.light_intensity))
        shadow = bool(rng.random() < v.shadow_probability)
        intensity = nominal * norm * scale
        add_light(spec, k, p.tolist(), intensity, castshadow=shadow)
        out.append({"pos": _f(p), "intensity": intensity, "intensity_scale": scale, "castshadow": shadow})
    return out


def _move_scene_camera(spec: mujoco.MjSpec, v: VisualDR, rng: np.random.Generator) -> dict | None:
    """ADDS position jitter, a small rotation (x, y, z in the camera frame) and a fovy offset."""
    cam = spec.camera(SCENE_CAMERA)
    if cam is None:
        return None
    dpos = rng.uniform(-v.camera_pos_jitter, v.camera_pos_jitter, 3)
    drot_deg = rng.uniform(-v.camera_rot_jitter, v.camera_rot_jitter, 3)
    dfovy = float(rng.uniform(-v.camera_fovy_jitter, v.camera_fovy_jitter))
    delta, quat = np.zeros(4), np.zeros(4)
    mujoco.mju_euler2Quat(delta, np.deg2rad(drot_deg), "xyz")  # intrinsic x, y, z: the camera's own axes
    mujoco.mju_mulQuat(quat, np.array(cam.quat, float), delta)
    cam.pos = (np.array(cam.pos, float) + dpos).tolist()
    cam.quat = quat.tolist()
    cam.fovy = float(cam.fovy) + dfovy
    return {"pos": _f(cam.pos), "quat": _f(cam.quat), "fovy": float(cam.fovy), "dpos": _f(dpos),
            "drot_deg": _f(drot_deg), "dfovy": dfovy}


def _move_wrist_camera(spec: mujoco.MjSpec, v: VisualDR, rng: np.random.Generator) -> dict | None:
    """ADDS a small mounting error to the wrist camera's position (a re-mounted bracket)."""
    cam = spec.camera(WRIST_CAMERA)
    if cam is None:
        return None
    dpos = rng.uniform(-v.wrist_camera_jitter, v.wrist_camera_jitter, 3)
    cam.pos = (np.array(cam.pos, float) + dpos).tolist()
    return {"pos": _f(cam.pos), "dpos": _f(dpos)}


# -- physics -----------------------------------------------------------------------------------------
def _free_bodies(spec: mujoco.MjSpec) -> list:
    """Movable task objects: bodies with a free joint, in spec order (which is the sampling order)."""
    return [b for b in spec.bodies if any(j.type == mujoco.mjtJoint.mjJNT_FREE for j in b.joints)]


def _scale_friction(spec: mujoco.MjSpec, r, rng: np.random.Generator) -> dict:
    """SCALES sliding friction of the table and of each free object (one factor per body, all its geoms).
    The gripper pads keep theirs: the pad/object pair still varies through the object's friction."""
    out = {}
    table = spec.geom("table")
    if table is not None:
        s = float(rng.uniform(*r))
        table.friction = [table.friction[0] * s, table.friction[1], table.friction[2]]
        out["table"] = s
    for body in _free_bodies(spec):
        s = float(rng.uniform(*r))
        for g in body.geoms:
            g.friction = [g.friction[0] * s, g.friction[1], g.friction[2]]
        out[body.name] = s
    return out


def _scale_mass(spec: mujoco.MjSpec, r, rng: np.random.Generator) -> dict:
    """SCALES each free object's mass (explicit body inertial, else each geom's mass or density), so the
    compiled inertia scales with it and the shape stays the same."""
    out = {}
    for body in _free_bodies(spec):
        s = float(rng.uniform(*r))
        if body.explicitinertial:
            body.mass = body.mass * s
            body.inertia = (np.array(body.inertia, float) * s).tolist()
        else:
            for g in body.geoms:
                if np.isnan(g.mass) or g.mass < 0:
                    g.density = g.density * s
                else:
                    g.mass = g.mass * s
        out[body.name] = s
    return out


def _scale_damping(spec: mujoco.MjSpec, r, rng: np.random.Generator) -> dict:
    """SCALES each arm joint's damping: the joint's passive damping AND its servo's velocity gain kv
    (biasprm[2] = -kv). Menagerie's UR5e has zero passive damping; all its damping is the servo's kv."""
    out = {}
    for jname, aname in zip(ARM_JOINTS, ARM_ACTUATORS):
        joint = spec.joint(jname)
        if joint is None:
            continue
        s = float(rng.uniform(*r))
        joint.damping = (np.array(joint.damping, float) * s).tolist()
        act = spec.actuator(aname)
        if act is not None and act.biastype == mujoco.mjtBias.mjBIAS_AFFINE:
            bias = np.array(act.biasprm, float)
            bias[2] *= s
            act.biasprm = bias.tolist()
        out[jname] = s
    return out


def _scale_gains(spec: mujoco.MjSpec, r, rng: np.random.Generator) -> dict:
    """SCALES each arm servo's stiffness kp: gainprm[0] and biasprm[1] (= -kp) together, so the actuator
    stays a position servo (force = kp*(ctrl - q) - kv*qd) that settles on its target."""
    out = {}
    for aname in ARM_ACTUATORS:
        act = spec.actuator(aname)
        if act is None:
            continue
        s = float(rng.uniform(*r))
        gain, bias = np.array(act.gainprm, float), np.array(act.biasprm, float)
        gain[0] *= s
        if act.biastype == mujoco.mjtBias.mjBIAS_AFFINE:
            bias[1] *= s
        act.gainprm, act.biasprm = gain.tolist(), bias.tolist()
        out[aname] = s
    return out


# -- the entry point ---------------------------------------------------------------------------------
def randomize_spec(spec: mujoco.MjSpec, cfg: DRConfig | str, visual_rng: np.random.Generator,
                   physics_rng: np.random.Generator) -> dict:
    """Randomize `spec` in place (before compile) and return the record of every sampled value.

    Blocks, in order: visual = textures, lights, scene camera, wrist camera; physics = friction, mass,
    joint damping, servo gains. Call it after the task has added its objects (friction/mass act on them),
    with fresh streams (`episode_rngs(seed).visual/.physics`): it spawns 4 children from each.
    """
    cfg = cfg if isinstance(cfg, DRConfig) else load_dr(cfg)
    v, p = cfg.visual, cfg.physics
    vis_rngs = visual_rng.spawn(4)
    phys_rngs = physics_rng.spawn(4)
    visual: dict = {}
    if _textures_active(v):
        visual["surfaces"] = _retexture(spec, v, vis_rngs[0])
    if _lights_active(v):
        visual["lights"] = _relight(spec, v, vis_rngs[1])
    if v.camera_pos_jitter or v.camera_rot_jitter or v.camera_fovy_jitter:
        visual["scene_camera"] = _move_scene_camera(spec, v, vis_rngs[2])
    if v.wrist_camera_jitter:
        visual["wrist_camera"] = _move_wrist_camera(spec, v, vis_rngs[3])
    physics: dict = {}
    for i, (key, fn) in enumerate((("friction_scale", _scale_friction), ("mass_scale", _scale_mass),
                                   ("joint_damping_scale", _scale_damping),
                                   ("actuator_gain_scale", _scale_gains))):
        if getattr(p, key) != (1.0, 1.0):
            physics[key] = fn(spec, getattr(p, key), phys_rngs[i])
    changed = sorted(visual) + sorted(physics)
    return {"preset": cfg.preset, "unchanged": not changed, "changed": changed,
            "light_count": len(visual["lights"]) if "lights" in visual else sum(
                1 for lt in spec.lights if lt.name.startswith("light")),
            "visual": visual, "physics": physics}


# -- sensors -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SensorParams:
    """One episode's sensor imperfections, sampled once and used by the camera and arm twins."""

    image_noise_std: float = 0.0  # gaussian noise, intensity levels (0..255 scale)
    color_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)  # per-channel white-balance error
    latency: float = 0.0  # s, mean frame latency
    latency_jitter: float = 0.0  # s, per-frame extra latency half-width
    q_noise_std: float = 0.0  # rad, joint encoder noise
    qd_noise_std: float = 0.0  # rad/s, joint velocity noise

    def record(self) -> dict:
        return asdict(self)


def sample_sensor_params(cfg: SensorDR, rng: np.random.Generator) -> SensorParams:
    """SETS the episode's sensor parameters from the ranges (noise std, gains, latency); stds pass through."""
    return SensorParams(
        image_noise_std=float(rng.uniform(*cfg.image_noise_std)),
        color_gain=tuple(float(g) for g in 1.0 + rng.uniform(-cfg.color_gain_jitter, cfg.color_gain_jitter, 3)),
        latency=float(rng.uniform(*cfg.latency)),
        latency_jitter=float(cfg.latency_jitter),
        q_noise_std=float(cfg.q_noise_std),
        qd_noise_std=float(cfg.qd_noise_std),
    )


def episode_sensor_params(episode) -> SensorParams:
    """The episode's sensor parameters, drawn first from its sensor stream: the recorder, the preview and the live
    sim cameras of one seed all get the same ones (and the stream then serves their per-frame noise)."""
    return sample_sensor_params(episode.dr.sensor, episode.rngs.sensor)


def corrupt_image(img: np.ndarray, params: SensorParams, rng: np.random.Generator) -> np.ndarray:
    """Per-channel gain, then additive gaussian noise, rounded and clipped back to uint8 (same shape)."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise TypeError(f"corrupt_image expects a uint8 image, got {img.dtype}")
    gain = np.asarray(params.color_gain, np.float32)
    if params.image_noise_std <= 0.0 and np.all(gain == 1.0):
        return img.copy()
    out = img.astype(np.float32)
    if img.ndim == 3 and img.shape[-1] >= 3:
        out[..., :3] *= gain
    else:
        out *= float(gain.mean())
    if params.image_noise_std > 0.0:
        out += rng.normal(0.0, params.image_noise_std, img.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


__all__ = ["randomize_spec", "SensorParams", "sample_sensor_params", "episode_sensor_params", "corrupt_image",
           "EpisodeRngs", "episode_rngs"]
