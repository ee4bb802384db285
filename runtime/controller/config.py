"""ControllerConfig: every knob of the chunk controller, typed and range-checked like the rest of sudd.

Why these defaults:
* `execution_latency` 0.016 s: measured on the twin (UR5e 500 Hz and UR5 125 Hz) with the servo settings
  below: line-tracking error is smallest there (p50 < 0.1 mm at 0.1 m/s, vs 1.6 mm with no compensation).
  The cross-correlation estimate (`ControllerLoop.latency_estimate()`, UMI's method) reads 14-15 ms: the
  correlation peak of a first-order lag (servo_j's tau = lookahead * 300 / gain = 15 ms) lies a little below
  its mean delay. On a real UR with lookahead 0.1 / gain 300 UMI measured ~100 ms end to end; set it from
  the estimate on the real arm (or turn on `adapt_latency`).
* `blend_time` 0.15 s: the brief's 100-200 ms window; it is lengthened automatically when the old and the
  new trajectory differ so much that a 0.15 s blend would need more than `budget` of a joint's jerk,
  acceleration or velocity limit (up to `max_blend_time`).
* servo lookahead 0.05 s / gain 1000: the stream is already C2-smooth at the servo rate, so the robot's own
  smoothing (which adds lag) can be light.
* gripper hysteresis 0.4 / 0.6: the policy's channel is a regressed 0..1 value that hovers near 0.5 while
  it is undecided; a band keeps the fingers from chattering. With more than two `gripper_levels` the band is
  the same fraction of the gap between each two neighbouring levels.
* `gripper_levels` None: the positions the policy bundle's data commanded (its manifest's
  `data.gripper_levels`; open and closed when it records none). A collector that opens the fingers half-way
  to reach between a drawer handle and the drawer front records 0.5; a binary channel could never execute it,
  and the policy, seeing fingers its data never had, wandered off (policy/EXPERIMENTS.md, "Gripper levels").
* `contact_yield_n` 0 (off): a steady press into the cabinet settles at 22 N with it (40 N) against 243 N
  without (tests/test_controller_contact.py), but the drawer episodes' protective stops are impacts, not
  presses: the fingers reach 150-770 N within a physics step of touching the front, before any measured force
  can act. With it, famfz_w2 completed 8/20 drawer_open and 8/20 drawer_close on seeds 100000-100019, against
  10/20 and 10/20 without (the same 6 ms latency; policy/EXPERIMENTS.md, "Contact yield"). Since the guard hugs
  the turned cabinet (sim/fixtures.py) the drawer stops are slow presses instead: a finger the handle tipped back
  lies on the cabinet's top and the arm goes on down. `contact_yield_axes = "up"` gives way to such presses only,
  not to the pull and push that move a drawer: step 28 then completes drawer_open 20/20 (18 without) and 83 of
  the seen 100 as without, but drawer_put 15 of its 40 seeds against 19, the handle pressed from above at 40-90 N
  when taken (policy/EXPERIMENTS.md, "A press from above"). So it stays off by default.
* `catch_up_periods` 5: the filter's stream moves one period of motion per step. A cycle that wakes late (a
  loaded host: 75-90 % of the cycles on time with the sim twin, policy and renderer on 2 cores) used to step
  it once, so the arm fell behind its plan and the filter's catch-up then ran it faster than planned, into the
  drawer handle: with 20 % of the cycles skipped in lockstep, drawer_open fell from 7/8 to 3/8, five of the
  failures contact-force stops (policy/EXPERIMENTS.md, "Late control cycles"). Stepping the missed periods
  (each within every limit) keeps the stream on the clock; past 5 periods (10 ms at 500 Hz) a gap is a stall.
* `reopen_empty_grasp` on, `reopen_hold` 2 s: on 120 held-out heavy-DR seeds the shipped policy completed
  78 pick-and-places with it against 64 without (14 gained, none lost); 2 s is about one approach.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from sim.config import ConfigError, load_toml, spec, validate


@dataclass(frozen=True)
class ControllerConfig:
    execution_latency: float = field(default=0.016, metadata=spec(0.0, 0.5, "s",
                                     doc="targets are commanded this much before their action time"))
    adapt_latency: bool = field(default=False, metadata=spec(doc="follow the online latency estimate"))
    latency_slew: float = field(default=0.002, metadata=spec(0.0, 0.1, "s/s",
                                doc="how fast an adapted latency may change (keeps the stream smooth)"))
    latency_window: float = field(default=2.0, metadata=spec(0.2, 10.0, "s", doc="cross-correlation window"))
    blend_time: float = field(default=0.15, metadata=spec(0.01, 1.0, "s", doc="old->new chunk blend window"))
    max_blend_time: float = field(default=1.5, metadata=spec(0.01, 5.0, "s"))
    budget: float = field(default=0.5, metadata=spec(0.05, 1.0,
                          doc="fraction of the safety limits a blend may use (jerk, accel, velocity)"))
    max_start_offset: float = field(default=0.3, metadata=spec(0.0, 3.2, "rad",
                                    doc="a chunk's first knot this far from the trajectory: rejected"))
    jump_factor: float = field(default=3.0, metadata=spec(1.0, 20.0,
                               doc="knot-to-knot joint step allowed: factor x velocity limit x interval"))
    jump_slack: float = field(default=0.02, metadata=spec(0.0, 1.0, "rad", doc="added to that step bound"))
    ik_tolerance: float = field(default=1e-4, metadata=spec(1e-9, 0.01, "m",
                                doc="IK result must reproduce the target this well (rad for rotation x 10)"))
    servo_lookahead: float = field(default=0.05, metadata=spec(0.03, 0.2, "s"))
    servo_gain: float = field(default=1000.0, metadata=spec(100.0, 2000.0))
    gripper_close_above: float = field(default=0.6, metadata=spec(0.0, 1.0, doc=(
        "the channel moves up to the next level above this fraction of the gap between the two levels")))
    gripper_open_below: float = field(default=0.4, metadata=spec(0.0, 1.0, doc="and down below this fraction"))
    gripper_levels: tuple[float, ...] | None = field(default=None, metadata=spec(0.0, 1.0, doc=(
        "finger positions (0 open .. 1 closed) the channel snaps to, increasing, from 0 to 1; the last is a "
        "grasp (closed with `gripper_force`), the others position moves. None: the policy bundle's")))
    gripper_min_hold: float = field(default=0.0, metadata=spec(0.0, 5.0, "s", doc=(
        "after a close or open, ignore the opposite edge for this long: a grasp is not undone by one chunk "
        "that flickers open (the collector holds 0.6 s after closing)")))
    reopen_empty_grasp: bool = field(default=True, metadata=spec(doc=(
        "a close that the gripper reports caught nothing is undone: the fingers open and the policy may try "
        "again (runtime/controller/gripper.py)")))
    reopen_hold: float = field(default=2.0, metadata=spec(0.0, 10.0, "s", doc=(
        "after an empty close, the policy's close is ignored until its channel reads open or this long")))
    gripper_speed: float = field(default=0.08, metadata=spec(0.0, 0.15, "m/s"))
    gripper_force: float = field(default=40.0, metadata=spec(0.0, 235.0, "N"))
    contact_yield_n: float = field(default=0.0, metadata=spec(0.0, 140.0, "N", doc=(
        "measured tool force above which the commanded position gives way along it (contact_yield.py), "
        "e.g. 40; 0 (the default) turns it off. Below the robot's own force limit (150 N) so it acts first")))
    contact_yield_axes: str = field(default="xyz", metadata=spec(choices=("xyz", "up"), doc=(
        "which measured force the target gives way to: xyz, any; up, only a press from above (the force's upward "
        "part), so the pull and push that move a drawer are not yielded to")))
    contact_yield_gain: float = field(default=0.002, metadata=spec(0.0, 0.1, "m/(N s)",
                                      doc="retreat speed per newton over contact_yield_n"))
    contact_yield_speed: float = field(default=0.1, metadata=spec(0.0, 0.5, "m/s", doc="the most retreat speed"))
    contact_return_speed: float = field(default=0.02, metadata=spec(0.0, 0.5, "m/s", doc=(
        "how fast the offset goes back to the plan once the force is below half of contact_yield_n")))
    contact_max_offset: float = field(default=0.04, metadata=spec(0.0, 0.2, "m", doc=(
        "the most the position gives way; a plan further into the contact meets the robot's force limit")))
    stop_timeout: float = field(default=2.0, metadata=spec(0.05, 30.0, "s", doc="stop(): give up after"))
    servo_stop_decel: float = field(default=10.0, metadata=spec(0.1, 40.0, "rad/s^2"))
    rest_speed: float = field(default=2e-3, metadata=spec(0.0, 0.1, "rad/s", doc="at rest below this"))
    late_tolerance: float = field(default=0.25, metadata=spec(0.0, 10.0,
                                  doc="a cycle starting later than this fraction of a period is late"))
    catch_up_periods: int = field(default=5, metadata=spec(0, 25, doc=(
        "a cycle up to this many periods late first steps the safety filter through the periods it missed, "
        "so the commanded stream keeps the clock; 0: one filter step per cycle, however late")))
    telemetry_size: int = field(default=4096, metadata=spec(16, 1_000_000))
    max_events: int = field(default=1000, metadata=spec(10, 1_000_000))

    def validate(self) -> None:
        validate(self)
        if self.gripper_open_below >= self.gripper_close_above:
            raise ConfigError(f"gripper_open_below = {self.gripper_open_below} must be below gripper_close_above = "
                              f"{self.gripper_close_above} (the hysteresis band)")
        levels = self.gripper_levels
        if levels is not None and (len(levels) < 2 or levels[0] != 0.0 or levels[-1] != 1.0
                                   or any(b <= a for a, b in zip(levels, levels[1:]))):
            raise ConfigError(f"gripper_levels = {list(levels)}: expected increasing finger positions from 0.0 "
                              "(open) to 1.0 (closed), e.g. [0.0, 0.5, 1.0]; leave it out to take the bundle's")
        if self.max_blend_time < self.blend_time:
            raise ConfigError(f"max_blend_time = {self.max_blend_time} must be >= blend_time = {self.blend_time}")


def load_controller(path) -> ControllerConfig:
    """`sudd run/eval --controller FILE`: a TOML file of ControllerConfig fields, the rest left at their
    defaults; an unknown field or a value out of range is a ConfigError that names it."""
    return load_toml(ControllerConfig, path)


def with_bundle_levels(cfg: ControllerConfig, manifest: dict) -> ControllerConfig:
    """`cfg` with the policy bundle's gripper levels (its manifest's `data.gripper_levels`, recorded by
    `sudd train` from the commands its data used) where `cfg` leaves them to the bundle; open and closed for a
    bundle that records none. Levels out of shape are a ConfigError naming the bundle's field."""
    if cfg.gripper_levels is not None:
        return cfg
    levels = (manifest.get("data") or {}).get("gripper_levels")
    if levels is None:
        return cfg
    try:
        out = dataclasses.replace(cfg, gripper_levels=tuple(float(v) for v in levels))
        out.validate()
    except (TypeError, ValueError) as e:
        raise ConfigError(f"policy bundle manifest data.gripper_levels = {levels!r}: {e}") from None
    return out


__all__ = ["ControllerConfig", "load_controller", "with_bundle_levels"]
