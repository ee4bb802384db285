"""Domain-randomization ranges: presets `off | light | heavy`, overridable field by field from TOML.

Every range is a (low, high) pair sampled uniformly; "scale" ranges multiply the nominal value, "jitter"
values are the half-width of an additive perturbation. `sudd sim preview` shows what a preset does.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from sim.config import ConfigError, load_config, load_toml, merge_flat, read_toml, spec

PRESETS = ("off", "light", "heavy")
Range = tuple[float, float]


@dataclass(frozen=True)
class VisualDR:
    retexture: bool = field(default=False, metadata=spec(doc="random procedural textures on table/floor/walls"))
    surface_value: Range = field(default=(1.0, 1.0), metadata=spec(0.0, 2.0, doc="brightness scale of surfaces"))
    surface_hue_jitter: float = field(default=0.0, metadata=spec(0.0, 0.5, doc="hue shift, fraction of the circle"))
    object_color_spread: float = field(default=0.0, metadata=spec(0.0, 1.0, doc="0 nominal shade, 1 whole class"))
    light_count: tuple[int, int] = field(default=(2, 2), metadata=spec(1, 6))
    light_intensity: Range = field(default=(1.0, 1.0), metadata=spec(0.0, 3.0, doc="scale of diffuse light"))
    light_pos_jitter: float = field(default=0.0, metadata=spec(0.0, 2.0, "m"))
    shadow_probability: float = field(default=1.0, metadata=spec(0.0, 1.0))
    camera_pos_jitter: float = field(default=0.0, metadata=spec(0.0, 0.2, "m"))
    camera_rot_jitter: float = field(default=0.0, metadata=spec(0.0, 15.0, "deg"))
    camera_fovy_jitter: float = field(default=0.0, metadata=spec(0.0, 10.0, "deg"))
    wrist_camera_jitter: float = field(default=0.0, metadata=spec(0.0, 0.02, "m"))

    def validate(self) -> None:
        _check_ranges(self, "visual")


@dataclass(frozen=True)
class PhysicsDR:
    friction_scale: Range = field(default=(1.0, 1.0), metadata=spec(0.1, 3.0))
    mass_scale: Range = field(default=(1.0, 1.0), metadata=spec(0.1, 5.0))
    joint_damping_scale: Range = field(default=(1.0, 1.0), metadata=spec(0.1, 5.0))
    actuator_gain_scale: Range = field(default=(1.0, 1.0), metadata=spec(0.5, 2.0))

    def validate(self) -> None:
        _check_ranges(self, "physics")


@dataclass(frozen=True)
class SensorDR:
    image_noise_std: Range = field(default=(0.0, 0.0), metadata=spec(0.0, 30.0, "intensity levels"))
    color_gain_jitter: float = field(default=0.0, metadata=spec(0.0, 0.5, doc="per-channel gain 1 ± this"))
    latency: Range = field(default=(0.0, 0.0), metadata=spec(0.0, 0.5, "s", doc="frame latency"))
    latency_jitter: float = field(default=0.0, metadata=spec(0.0, 0.1, "s"))
    q_noise_std: float = field(default=0.0, metadata=spec(0.0, 0.01, "rad"))
    qd_noise_std: float = field(default=0.0, metadata=spec(0.0, 0.1, "rad/s"))

    def validate(self) -> None:
        _check_ranges(self, "sensor")


@dataclass(frozen=True)
class ObjectDR:
    xy_jitter: float = field(default=0.0, metadata=spec(0.0, 0.2, "m", doc="object position jitter"))
    yaw_jitter: float = field(default=0.0, metadata=spec(0.0, 3.1416, "rad"))
    size_scale: Range = field(default=(1.0, 1.0), metadata=spec(0.5, 1.5))

    def validate(self) -> None:
        _check_ranges(self, "objects")


@dataclass(frozen=True)
class DRConfig:
    preset: str = field(default="off", metadata=spec(choices=PRESETS))
    visual: VisualDR = field(default_factory=VisualDR)
    physics: PhysicsDR = field(default_factory=PhysicsDR)
    sensor: SensorDR = field(default_factory=SensorDR)
    objects: ObjectDR = field(default_factory=ObjectDR)


def _check_ranges(section, name: str) -> None:
    for key, value in vars(section).items():
        if isinstance(value, tuple) and len(value) == 2 and value[0] > value[1]:
            raise ConfigError(f"{name}.{key} = {list(value)}: the low end must not exceed the high end")


_LIGHT = DRConfig(
    preset="light",
    visual=VisualDR(retexture=False, surface_value=(0.85, 1.15), surface_hue_jitter=0.03, object_color_spread=0.4,
                    light_count=(1, 3), light_intensity=(0.8, 1.2), light_pos_jitter=0.3, shadow_probability=0.8,
                    camera_pos_jitter=0.01, camera_rot_jitter=1.0, camera_fovy_jitter=1.0, wrist_camera_jitter=0.002),
    physics=PhysicsDR(friction_scale=(0.9, 1.1), mass_scale=(0.9, 1.1), joint_damping_scale=(0.9, 1.1),
                      actuator_gain_scale=(0.95, 1.05)),
    sensor=SensorDR(image_noise_std=(0.0, 2.0), color_gain_jitter=0.03, latency=(0.0, 0.02), latency_jitter=0.003,
                    q_noise_std=1e-4, qd_noise_std=1e-3),
    objects=ObjectDR(xy_jitter=0.03, yaw_jitter=0.5, size_scale=(0.95, 1.05)),
)

_HEAVY = DRConfig(
    preset="heavy",
    visual=VisualDR(retexture=True, surface_value=(0.5, 1.4), surface_hue_jitter=0.5, object_color_spread=1.0,
                    light_count=(1, 4), light_intensity=(0.4, 1.6), light_pos_jitter=1.0, shadow_probability=0.6,
                    camera_pos_jitter=0.04, camera_rot_jitter=4.0, camera_fovy_jitter=4.0, wrist_camera_jitter=0.006),
    physics=PhysicsDR(friction_scale=(0.6, 1.4), mass_scale=(0.5, 2.0), joint_damping_scale=(0.5, 2.0),
                      actuator_gain_scale=(0.85, 1.15)),
    sensor=SensorDR(image_noise_std=(0.0, 8.0), color_gain_jitter=0.12, latency=(0.0, 0.06), latency_jitter=0.01,
                    q_noise_std=5e-4, qd_noise_std=5e-3),
    objects=ObjectDR(xy_jitter=0.07, yaw_jitter=3.1416, size_scale=(0.85, 1.15)),
)

_PRESET_CONFIGS = {"off": DRConfig(), "light": _LIGHT, "heavy": _HEAVY}


def preset(name: str) -> DRConfig:
    try:
        return _PRESET_CONFIGS[name]
    except KeyError:
        raise ConfigError(f"unknown DR preset {name!r}; expected one of {list(PRESETS)}") from None


def load_dr(name_or_path: str | DRConfig = "off", overrides: dict[str, Any] | None = None) -> DRConfig:
    """A preset name, or a TOML file whose optional `preset` key names the base it overrides."""
    if isinstance(name_or_path, DRConfig):
        base, data = name_or_path, {}
    elif str(name_or_path) in PRESETS:
        base, data = preset(str(name_or_path)), {}
    else:
        path = Path(name_or_path)
        if path.suffix != ".toml":
            raise ConfigError(f"--dr {name_or_path!r}: expected a preset {list(PRESETS)} or a .toml file")
        data = read_toml(path)
        base = preset(data.get("preset", "off"))

    if overrides:
        data = merge_flat(data, overrides)
    cfg = load_config(DRConfig, data, where=str(name_or_path) if data else "", base=base)
    return replace(cfg, preset=data.get("preset", base.preset))


__all__ = ["DRConfig", "VisualDR", "PhysicsDR", "SensorDR", "ObjectDR", "PRESETS", "preset", "load_dr", "load_toml"]
