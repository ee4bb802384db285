"""Safety limits: typed, validated, loadable from TOML, with safe defaults for a UR5e/UR5 carrying a 2F-85.

    limits = default_limits("ur5e")
    limits = load_limits("cell.toml", "ur5e", {"tcp.max_linear_speed": 0.1})

Every field carries its allowed range (`sim.config.spec`); `SafetyLimits.validate` then checks what a range
cannot: the joint limits against the robot's, velocities against its maximum, and that the limits can be
held together in discrete time (jerk * dt <= acceleration, jerk * velocity >= acceleration^2, a joint range
wide enough to stop in). Units: metres, radians, seconds; poses in the robot base frame (table top z = 0).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from sim.config import ConfigError, load_config, merge_flat, spec

Vec6 = tuple[float, float, float, float, float, float]
Vec3 = tuple[float, float, float]
Box = tuple[float, float, float, float, float, float]  # (xmin, ymin, zmin, xmax, ymax, zmax)

VARIANT_NAMES = ("ur5e", "ur5")

# Points of the 2F-85 fingers in the TCP frame (z along the approach direction, x across the finger gap).
# Open, they bound the pads at every closure: the pads reach 17.7 mm past the TCP when closed on nothing and
# +-50.6 mm across when open (measured on sim.robot's model; tests check the bound).
GRIPPER_POINTS_2F85: tuple[Vec3, ...] = (
    (0.052, 0.014, 0.018), (0.052, -0.014, 0.018), (-0.052, 0.014, 0.018), (-0.052, -0.014, 0.018),
)
# The same points with the fingers closed. Between, the points move linearly with the closure, and the pads
# follow an arc that bulges outward of that line (+-30.4 mm at half closure, the line's 30.6 mm): 10 mm,
# not the pads' 8.8 mm, keeps the line outside the arc everywhere (tests check it at every tenth).
GRIPPER_POINTS_2F85_CLOSED: tuple[Vec3, ...] = (
    (0.010, 0.014, 0.018), (0.010, -0.014, 0.018), (-0.010, 0.014, 0.018), (-0.010, -0.014, 0.018),
)


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits of the commanded stream (shoulder_pan .. wrist_3)."""

    lower: Vec6 = field(default=(-2 * math.pi,) * 6, metadata=spec(-2 * math.pi, 2 * math.pi, "rad",
                                                                 doc="robot joint limits (defaults: the variant's)"))
    upper: Vec6 = field(default=(2 * math.pi,) * 6, metadata=spec(-2 * math.pi, 2 * math.pi, "rad"))
    position_margin: float = field(default=0.05, metadata=spec(0.0, 0.5, "rad",
                                                              doc="kept clear inside lower/upper"))
    velocity: Vec6 = field(default=(1.0, 1.0, 1.0, 1.5, 1.5, 1.5), metadata=spec(0.01, 3.2, "rad/s"))
    acceleration: Vec6 = field(default=(5.0, 5.0, 5.0, 10.0, 10.0, 10.0), metadata=spec(0.1, 100.0, "rad/s^2"))
    jerk: Vec6 = field(default=(150.0, 150.0, 150.0, 300.0, 300.0, 300.0), metadata=spec(1.0, 1e5, "rad/s^3"))
    max_tracking_error: float = field(default=0.15, metadata=spec(0.001, 1.0, "rad",
                                                                  doc="measured vs commanded; beyond: stop"))

    @property
    def soft_lower(self) -> tuple[float, ...]:
        return tuple(lo + self.position_margin for lo in self.lower)

    @property
    def soft_upper(self) -> tuple[float, ...]:
        return tuple(hi - self.position_margin for hi in self.upper)


@dataclass(frozen=True)
class WorkspaceLimits:
    """Where the TCP and the finger points may be. Targets are kept `target_margin` inside these limits."""

    box_min: Vec3 = field(default=(-0.70, 0.0, 0.0), metadata=spec(-2.0, 2.0, "m", doc="TCP box, base frame"))
    box_max: Vec3 = field(default=(0.70, 0.90, 0.80), metadata=spec(-2.0, 2.0, "m"))
    table_z: float = field(default=0.0, metadata=spec(-1.0, 1.0, "m", doc="height of the table plane"))
    finger_clearance: float = field(default=0.003, metadata=spec(0.0, 0.2, "m",
                                                                doc="finger points stay this far above the table"))
    target_margin: float = field(default=0.005, metadata=spec(0.0, 0.1, "m"))
    keepout: tuple[Box, ...] = field(default=(), metadata=spec(doc="boxes no TCP/finger point may enter, "
                                                                   "[xmin, ymin, zmin, xmax, ymax, zmax] each"))
    gripper_points: tuple[Vec3, ...] = field(default=GRIPPER_POINTS_2F85,
                                             metadata=spec(doc="points in the TCP frame checked against "
                                                               "the table and keep-out boxes, fingers open"))
    gripper_points_closed: tuple[Vec3, ...] = field(
        default=GRIPPER_POINTS_2F85_CLOSED,
        metadata=spec(doc="the same points with the fingers closed: between, the points move linearly with "
                          "the least closure the fingers can have until the next gripper command (0 open .. "
                          "1 closed, from the controller); [] checks the open points always"))


@dataclass(frozen=True)
class TcpLimits:
    max_linear_speed: float = field(default=0.25, metadata=spec(0.001, 2.0, "m/s",
                                                               doc="0.25 m/s: collaborative reduced speed"))
    max_angular_speed: float = field(default=1.0, metadata=spec(0.01, 6.0, "rad/s"))


@dataclass(frozen=True)
class CommandLimits:
    max_age: float = field(default=0.100, metadata=spec(0.001, 2.0, "s", doc="older commands: stop and hold"))
    max_future: float = field(default=0.050, metadata=spec(0.0, 1.0, "s",
                                                          doc="tolerated clock skew (command time > now)"))
    event_gap: float = field(default=0.100, metadata=spec(0.0, 10.0, "s",
                                                         doc="an intervention absent this long ends its event"))


@dataclass(frozen=True)
class CollisionLimits:
    enabled: bool = field(default=True)
    slow_distance: float = field(default=0.03, metadata=spec(0.001, 0.5, "m", doc="full speed beyond this"))
    stop_distance: float = field(default=0.005, metadata=spec(0.0, 0.2, "m", doc="stop before this distance"))
    rate_hz: float = field(default=100.0, metadata=spec(1.0, 1000.0, "Hz", doc="check rate; scale held between"))
    self_collision: bool = field(default=True)


@dataclass(frozen=True)
class GripperLimits:
    max_speed: float = field(default=0.10, metadata=spec(0.0, 0.15, "m/s", doc="2F-85: 0.02-0.15 m/s"))
    max_force: float = field(default=60.0, metadata=spec(0.0, 235.0, "N", doc="2F-85: 20-235 N"))
    max_opening: float = field(default=0.085, metadata=spec(0.0, 0.085, "m"))


@dataclass(frozen=True)
class RecoveryLimits:
    protective_wait: float = field(default=5.0, metadata=spec(0.0, 60.0, "s",
                                                             doc="the controller refuses to unlock earlier"))


@dataclass(frozen=True)
class SafetyLimits:
    variant: str = field(default="ur5e", metadata=spec(choices=VARIANT_NAMES))
    joints: JointLimits = field(default_factory=JointLimits)
    workspace: WorkspaceLimits = field(default_factory=WorkspaceLimits)
    tcp: TcpLimits = field(default_factory=TcpLimits)
    command: CommandLimits = field(default_factory=CommandLimits)
    collision: CollisionLimits = field(default_factory=CollisionLimits)
    gripper: GripperLimits = field(default_factory=GripperLimits)
    recovery: RecoveryLimits = field(default_factory=RecoveryLimits)

    def validate(self) -> None:
        """Cross-field checks; raises ConfigError naming the field, the value and what is allowed."""
        from sim.robot import get_variant

        v = get_variant(self.variant)
        j = self.joints
        dt = v.control_period
        for i in range(6):
            if j.lower[i] < v.joint_lower[i] - 1e-9 or j.upper[i] > v.joint_upper[i] + 1e-9:
                raise ConfigError(f"joints.lower/upper[{i}] = [{j.lower[i]}, {j.upper[i]}] exceeds the {v.name}'s "
                                  f"joint range [{v.joint_lower[i]:.4f}, {v.joint_upper[i]:.4f}] rad")
            if j.velocity[i] > v.max_joint_velocity[i] + 1e-9:
                raise ConfigError(f"joints.velocity[{i}] = {j.velocity[i]} exceeds the {v.name}'s maximum "
                                  f"{v.max_joint_velocity[i]:.4f} rad/s")
            if j.jerk[i] * dt > j.acceleration[i]:
                raise ConfigError(f"joints.jerk[{i}] = {j.jerk[i]}: one {dt * 1e3:.0f} ms cycle at this jerk exceeds "
                                  f"joints.acceleration[{i}] = {j.acceleration[i]}; need jerk <= "
                                  f"{j.acceleration[i] / dt:.1f} rad/s^3")
            if j.jerk[i] * j.velocity[i] < j.acceleration[i] ** 2:
                raise ConfigError(f"joints.jerk[{i}] = {j.jerk[i]} is too low for acceleration {j.acceleration[i]} "
                                  f"at velocity {j.velocity[i]}: need jerk >= acceleration^2 / velocity = "
                                  f"{j.acceleration[i] ** 2 / j.velocity[i]:.1f} rad/s^3")
            span = j.upper[i] - j.lower[i] - 2 * j.position_margin
            need = 2 * stop_distance_bound(j.velocity[i], j.acceleration[i], j.jerk[i], dt)
            if span < need:
                raise ConfigError(f"joints: joint {i} range {span:.3f} rad inside the margins is narrower than "
                                  f"twice its stopping distance at full speed ({need:.3f} rad)")
        w = self.workspace
        if any(lo >= hi for lo, hi in zip(w.box_min, w.box_max)):
            raise ConfigError(f"workspace.box_min {list(w.box_min)} must be below box_max {list(w.box_max)} "
                              "on every axis")
        if w.box_max[2] <= w.table_z + w.finger_clearance + 2 * w.target_margin:
            raise ConfigError(f"workspace.box_max z = {w.box_max[2]} leaves no room above the table plane "
                              f"{w.table_z} + finger_clearance {w.finger_clearance}")
        for k, b in enumerate(w.keepout):
            if not all(math.isfinite(x) for x in b) or any(b[i] >= b[i + 3] for i in range(3)):
                raise ConfigError(f"workspace.keepout[{k}] = {list(b)}: expected [xmin, ymin, zmin, xmax, ymax, "
                                  "zmax] with each min below its max")
        for k, p in enumerate(w.gripper_points):
            if not all(math.isfinite(x) and abs(x) <= 0.5 for x in p):
                raise ConfigError(f"workspace.gripper_points[{k}] = {list(p)}: each coordinate within 0.5 m")
        if w.gripper_points_closed and len(w.gripper_points_closed) != len(w.gripper_points):
            raise ConfigError(f"workspace.gripper_points_closed has {len(w.gripper_points_closed)} points, "
                              f"gripper_points {len(w.gripper_points)}: give the same points closed, in the same "
                              "order, or [] to check the open points always")
        for k, p in enumerate(w.gripper_points_closed):
            if not all(math.isfinite(x) and abs(x) <= 0.5 for x in p):
                raise ConfigError(f"workspace.gripper_points_closed[{k}] = {list(p)}: each coordinate within "
                                  "0.5 m")
        c = self.collision
        if c.stop_distance >= c.slow_distance:
            raise ConfigError(f"collision.stop_distance {c.stop_distance} must be below "
                              f"collision.slow_distance {c.slow_distance}")


def stop_distance_bound(v: float, a_max: float, j_max: float, dt: float) -> float:
    """Upper bound of the distance a joint moving at v (zero acceleration) travels while it stops.

    The same bound as `safety.joint_limits.JointLimiter.stop_bound` (from rest acceleration 0); kept here
    so the config check needs no limiter.
    """
    c = j_max / a_max
    vp = abs(v)
    t1 = min(a_max, c * vp) / j_max + dt
    w = a_max / c
    d = vp * t1
    return d + ((vp * vp - w * w) / (2 * a_max) + w / c if vp > w else vp / c)


def default_limits(variant: str = "ur5e") -> SafetyLimits:
    """Safe defaults for `variant` ("ur5e" 500 Hz or "ur5" CB3 125 Hz): its joint range, reduced speeds."""
    from sim.robot import get_variant

    v = get_variant(variant)
    joints = replace(JointLimits(), lower=tuple(float(x) for x in v.joint_lower),
                     upper=tuple(float(x) for x in v.joint_upper))
    limits = SafetyLimits(variant=v.name, joints=joints)
    limits.validate()
    return limits


def load_limits(path: str | Path | None = None, variant: str | None = None,
                overrides: dict[str, Any] | None = None) -> SafetyLimits:
    """Defaults for the variant, then a TOML file (optional), then flat dotted overrides ("tcp.max_linear_speed").

    The variant comes from `variant`, else the file's `variant` key, else "ur5e"; a file naming another
    variant than the one asked for is an error (its joint limits would be the wrong robot's).
    """
    data: dict[str, Any] = {}
    where = ""
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"safety limits file {path} does not exist; pass the path of a TOML file")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path} is not valid TOML: {exc}") from exc
        where = str(path)
    if overrides:
        data = merge_flat(data, overrides)
    file_variant = data.get("variant")
    if variant is not None and file_variant is not None and file_variant != variant:
        raise ConfigError(f"{where or 'overrides'}: variant = {file_variant!r} but the robot is {variant!r}")
    name = variant or file_variant or "ur5e"
    if name not in VARIANT_NAMES:
        raise ConfigError(f"variant = {name!r} is not allowed; expected one of {list(VARIANT_NAMES)}")
    return load_config(SafetyLimits, data, where=where, base=default_limits(name))


__all__ = ["SafetyLimits", "JointLimits", "WorkspaceLimits", "TcpLimits", "CommandLimits", "CollisionLimits",
           "GripperLimits", "RecoveryLimits", "GRIPPER_POINTS_2F85", "GRIPPER_POINTS_2F85_CLOSED", "default_limits",
           "load_limits", "stop_distance_bound", "ConfigError"]
