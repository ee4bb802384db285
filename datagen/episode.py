"""One data-generation episode: plan from language, run primitives, verify each subtask, retry, record.

The loop of "Scaling Up and Distilling Down": the planner splits the instruction into subtasks; each runs a
sampling-based primitive, then its success-check snippet in the sandbox. A failed check triggers a recovery
(open, retreat) and a retry with a fresh sample, so the data holds recoveries. The episode records both the
plan's own verdict and the task's ground-truth predicate, and says which one is the training label.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from datagen.dart import joint_offsets
from datagen.plan import PRIMITIVES, describe
from datagen.planner import make_planner
from datagen.primitives import GRASP_SECONDS, HANDLE_GRASPS, PrimitiveFailed, Primitives
from datagen.recorder import Recorder
from datagen.release_offsets import ReleaseOffsets
from datagen.sandbox import SandboxError, run_check
from datagen.schema import IMAGE_SIZE, PERTURBATION, EpisodeData
from datagen.trajectory import Motion, Segment, execute
from sim.build import build_episode
from sim.tasks import Holdout
from sim.tasks.base import OBJECT_COLORS, SHAPES
from sim.config import spec
from sim.state import StateView

log = logging.getLogger(__name__)
LABEL_SOURCES = ("ground_truth", "check")
GRIPPERS = ("driver", "servo")
SETTLE_S = 0.3


@dataclass(frozen=True)
class DatagenConfig:
    """How episodes are generated; recorded with every dataset."""

    dr: str = field(default="heavy", metadata=spec(doc="DR preset off|light|heavy or a TOML path"))
    fidelity: str = field(default="fast", metadata=spec(choices=("full", "fast")))
    image_size: tuple[int, int] = field(default=IMAGE_SIZE, metadata=spec(32, 512, "px"))
    max_retries: int = field(default=4, metadata=spec(0, 100, doc="retries per subtask"))
    label: str = field(default="ground_truth", metadata=spec(choices=LABEL_SOURCES,
                       doc="which verdict becomes the success label: the task predicate or the plan's checks"))
    planner: str = field(default="offline", metadata=spec(choices=("offline", "llm")))
    llm_url: str = ""
    llm_model: str = ""
    time_limit_factor: float = field(default=2.0, metadata=spec(0.5, 10.0,
                                     doc="episode sim-time budget as a multiple of the task's max_seconds"))
    perturb: float = field(default=0.0, metadata=spec(0.0, 1.0,
                           doc="probability that a place is disturbed (the object dropped on the way), so the "
                               "data holds recoveries; 0 leaves episodes exactly as without it"))
    perturb_grasp: float = field(default=0.0, metadata=spec(0.0, 1.0,
                                 doc="probability that a pick's gripper closes early, above the object (a "
                                     "missed grasp), so the data holds regrasps; 0 leaves episodes unchanged"))
    path_noise_cm: float = field(default=0.0, metadata=spec(0.0, 5.0, "cm", doc=(
        "DART noise injection (datagen/dart.py): the executed TCP path is pushed off the plan while it moves "
        "by a smooth random offset of this std per axis, the recorded actions stay the plan's, so the policy "
        "learns to steer back; 0 leaves episodes exactly as without it")))
    grasp_noise_cm: float = field(default=0.0, metadata=spec(0.0, 3.0, "cm", doc=(
        "each pick's grasp happens at a random horizontal offset of this std per axis from the planned one "
        "(datagen/dart.py), the recorded actions stay the plan's, so the policy learns to close when near, "
        "not only exactly on the plan; 0 leaves episodes exactly as without it")))
    gripper: str = field(default="driver", metadata=spec(choices=GRIPPERS, doc=(
        "how the fingers move: driver, as the 2F-85's driver moves them at gripper_speed and gripper_force "
        "(sim/finger_drive.py, as the runtime's gripper twin), holds lasting until they stop; servo, an instant "
        "full-force position servo (the collector before 2026-12-07: shut in 0.1 s with ~5x the squeeze)")))
    gripper_speed: float = field(default=0.08, metadata=spec(0.02, 0.15, "m/s",
                                 doc="finger speed with gripper = driver (the runtime's default, 80 mm/s)"))
    gripper_force: float = field(default=40.0, metadata=spec(20.0, 235.0, "N",
                                 doc="grip force with gripper = driver (the runtime's default, 40 N)"))
    handle_grasp: str = field(default="top", metadata=spec(choices=HANDLE_GRASPS, doc=(
        "how a drawer's handle is grasped: from above (the fingers closing across it horizontally) or from the "
        "front, level (the fingers closing above and below it, the gripper's outer links away from the drawer)")))
    holdout_colors: tuple[str, ...] = field(default=(), metadata=spec(choices=OBJECT_COLORS,
                                            doc="object colours never used (kept for a held-out evaluation)"))
    holdout_shapes: tuple[str, ...] = field(default=(), metadata=spec(choices=SHAPES,
                                            doc="object shapes never used (kept for a held-out evaluation)"))

    def holdout(self) -> Holdout:
        return Holdout(colors=tuple(self.holdout_colors), shapes=tuple(self.holdout_shapes))


MISSED = "perturbed: gripper closed above the object"


def _dropped(motion: Motion, rng: np.random.Generator) -> Motion:
    """The place motion cut 10-40 % of the way (in transit), where the gripper lets go (a slip or a bump)."""
    cut = motion.truncated(motion.duration * rng.uniform(0.1, 0.4))
    cut.append(Segment.hold(cut.final_q, 0.6, 0.0, PERTURBATION))
    return cut


def _missed(motion: Motion, rng: np.random.Generator) -> Motion:
    """The pick motion cut 50-90 % of the way (in time) down its approach, where the gripper closes on air a
    few centimetres above the grasp: a misjudged grasp, the distilled policies' commonest failure. The data
    then shows what follows one (open, back off, grasp again), not only grasps that work."""
    i = motion.labels.index("approach")
    start = sum(s.duration for s in motion.segments[:i])
    cut = motion.truncated(start + motion.segments[i].duration * rng.uniform(0.5, 0.9))
    cut.append(Segment.hold(cut.final_q, GRASP_SECONDS, 1.0, PERTURBATION))
    return cut


def _resume_point(plan, index: int, state) -> int:
    """After a recovery released the gripper, a place must start again from its pick."""
    sub = plan.subtasks[index]
    if sub.primitive == "place" and not state.holding(sub.args["object"]):
        for j in range(index - 1, -1, -1):
            prev = plan.subtasks[j]
            if prev.primitive == "pick" and prev.args["object"] == sub.args["object"]:
                return j
    return index


def run_episode(task: str, seed: int, cfg: DatagenConfig = DatagenConfig(), planner=None,
                holdout: Holdout | None = None) -> EpisodeData:
    """Generate the episode (task, seed); the same arguments always give the same episode.
    `holdout` overrides the config's (an evaluation runs the collector on held-out targets with it)."""
    holdout = holdout or cfg.holdout()
    ep = build_episode(task, seed, cfg.dr, cfg.fidelity, holdout=holdout)
    world = ep.world
    if cfg.gripper == "driver":
        world.drive_fingers(cfg.gripper_speed, cfg.gripper_force)
    scene = describe(ep.instance)
    planner = planner or make_planner(cfg.planner, llm_url=cfg.llm_url or None, llm_model=cfg.llm_model or None)
    plan = planner.plan(ep.instruction, scene).validate(scene)
    prims = Primitives(world, ep.rngs.policy, variant=world.variant.name, handle_grasp=cfg.handle_grasp)
    recorder = Recorder(ep, image_size=tuple(cfg.image_size))
    releases = ReleaseOffsets(recorder, world)
    state = StateView(world)
    budget = ep.task.max_seconds * cfg.time_limit_factor
    retries, attempts, completed = 0, [], 0
    # Its own stream, so that perturb = 0 leaves every other draw (and the episode) unchanged.
    perturb_rng = np.random.default_rng([int(seed), 0x5EED])
    dart_rng = np.random.default_rng([int(seed), 0xDA27])

    def run(motion: Motion, placing: str | None = None) -> None:
        offsets = None
        if cfg.path_noise_cm > 0 or cfg.grasp_noise_cm > 0:
            offsets = joint_offsets(motion, prims.kin, world.timestep, dart_rng, cfg.path_noise_cm / 100.0,
                                    grasp_sigma=cfg.grasp_noise_cm / 100.0)
        execute(world, motion, observer=recorder if placing is None else releases.placing(placing), offsets=offsets)

    tries = [0] * len(plan.subtasks)
    index = 0
    recorder.subtask = 0
    recorder.start()
    try:
        while index < len(plan.subtasks) and world.time <= budget:
            sub = plan.subtasks[index]
            recorder.subtask = index
            ok, executed, reason = False, False, ""
            try:
                motion = getattr(prims, sub.primitive)(*[sub.args[name] for name in PRIMITIVES[sub.primitive]])
                if sub.primitive == "place" and cfg.perturb and perturb_rng.random() < cfg.perturb:
                    motion = _dropped(motion, perturb_rng)
                    reason = "perturbed: object dropped during the place"
                elif sub.primitive == "pick" and cfg.perturb_grasp and perturb_rng.random() < cfg.perturb_grasp:
                    motion = _missed(motion, perturb_rng)
                    reason = MISSED
                executed = True
                run(motion, sub.args["object"] if sub.primitive == "place" else None)
                ok = run_check(sub.check, state, scene)
            except PrimitiveFailed as exc:
                reason = f"primitive failed: {exc}"
            except SandboxError as exc:
                reason = f"check rejected: {exc}"
            attempts.append({"subtask": index, "attempt": tries[index], "ok": ok, "executed": executed,
                             "reason": reason, "t": round(world.time, 3)})
            if ok:
                index += 1
                continue
            retries += 1
            tries[index] += 1
            if tries[index] > cfg.max_retries:
                break
            if executed or tries[index] % 2 == 0:
                # The world changed (or sampling keeps failing from here): recover — open, retreat, home — and
                # retry with a fresh sample. Recovery steps keep the subtask's label, so the policy learns them.
                try:
                    run(prims.reopen() if reason.startswith(MISSED) else prims.recover())
                except PrimitiveFailed as exc:
                    attempts[-1]["reason"] += f"; recovery failed: {exc}"
                index = _resume_point(plan, index, state)
        completed = index
        for _ in range(int(round(SETTLE_S / world.timestep))):  # let things come to rest before judging
            world.step()
            recorder(world)
        ground_truth = ep.success()
        check_ok = completed == len(plan.subtasks)
        if check_ok and plan.task_check:
            try:
                check_ok = run_check(plan.task_check, state, scene)
            except SandboxError:
                check_ok = False
        label = ground_truth if cfg.label == "ground_truth" else check_ok
        meta = {
            "task": task, "seed": int(seed), "instruction": ep.instruction,
            "subtasks": [s.text for s in plan.subtasks], "success": bool(ground_truth),
            "check_success": bool(check_ok), "label": {"value": bool(label), "source": cfg.label},
            "retries": retries, "planner": plan.planner, "dr": ep.dr_record, "attempts": attempts,
            "plan": plan.record(), "task_record": ep.instance.record(), "fidelity": cfg.fidelity,
            "sim_seconds": round(world.time, 3),
            "holdout": {"colors": list(holdout.colors), "shapes": list(holdout.shapes), "split": holdout.split},
        }
        if cfg.path_noise_cm > 0:  # only then: datasets made without it keep their content hash
            meta["path_noise_cm"] = cfg.path_noise_cm
        if cfg.grasp_noise_cm > 0:
            meta["grasp_noise_cm"] = cfg.grasp_noise_cm
        if cfg.gripper == "driver":  # datasets of the servo collector keep their content hash
            meta["gripper"] = {"speed_m_s": cfg.gripper_speed, "force_n": cfg.gripper_force}
        if cfg.handle_grasp != "top":
            meta["handle_grasp"] = cfg.handle_grasp
        if releases.records:  # where each placed object sat in the hand (datagen/release_offsets.py)
            meta["release_offsets"] = releases.records
        return recorder.finish(meta)
    finally:
        recorder.close()
