"""Build one episode's world from (task, seed, DR, fidelity, robot): the single way scenes are made.

Same arguments ⇒ bit-identical model and first frame: every random choice comes from the episode's seeded
streams (sim.seeding), in a fixed order.
"""

from __future__ import annotations

from dataclasses import dataclass

from sim.dr_config import DRConfig, load_dr
from sim.scene import base_scene
from sim.seeding import EpisodeRngs, episode_rngs
from sim.tasks import Holdout, TaskFamily, TaskInstance, get_task
from sim.world import World

SETTLE_SECONDS = 0.3  # let objects come to rest on the table before the episode starts


@dataclass
class Episode:
    """A built world with the task that set it up and the random streams it came from."""

    world: World
    task: TaskFamily | None
    instance: TaskInstance | None
    rngs: EpisodeRngs
    dr: DRConfig
    dr_record: dict

    @property
    def instruction(self) -> str:
        return self.instance.instruction if self.instance else ""

    def success(self) -> bool:
        from sim.state import StateView

        if self.task is None or self.instance is None:
            raise ValueError("this world was built without a task, so it has no success predicate")
        return bool(self.task.success(StateView(self.world), self.instance))

    def record(self) -> dict:
        return {"task": self.instance.record() if self.instance else None, "seed": self.rngs.seed,
                "dr_preset": self.dr.preset, "dr": self.dr_record, "robot": self.world.variant.name,
                "fidelity": self.world.info.get("fidelity")}


def build_episode(task: str | TaskFamily | None = None, seed: int = 0, dr: str | DRConfig = "off",
                  fidelity: str = "full", variant: str = "ur5e", holdout: Holdout = Holdout(),
                  settle: bool = True) -> Episode:
    from sim.fidelity import apply_fidelity
    from sim.randomize import randomize_spec

    family = get_task(task) if isinstance(task, str) else task
    cfg = load_dr(dr)
    rngs = episode_rngs(seed)
    spec = base_scene(variant)
    instance = None
    if family is not None:
        instance = _sample(family, rngs, cfg, holdout)
        family.build(spec, instance)
    apply_fidelity(spec, fidelity)
    dr_record = randomize_spec(spec, cfg, rngs.visual, rngs.physics)
    model = spec.compile()
    world = World(model, variant, info={"task": family.name if family else None, "seed": int(seed),
                                        "fidelity": fidelity, "dr_preset": cfg.preset})
    if family is not None:
        family.initialize(world, instance)
    if settle:
        world.step(int(round(SETTLE_SECONDS / world.timestep)))
        world.data.time = 0.0
    return Episode(world, family, instance, rngs, cfg, dr_record)


def _sample(family: TaskFamily, rngs: EpisodeRngs, cfg: DRConfig, holdout: Holdout) -> TaskInstance:
    instance = family.sample(rngs.layout, cfg, holdout)
    instance.seed = int(rngs.seed)
    return instance


def task_instance(task: str | TaskFamily, seed: int, dr: str | DRConfig = "off",
                  holdout: Holdout = Holdout()) -> TaskInstance:
    """The task instance `build_episode` would set up (the same objects, targets and instruction), without
    building its world: the layout draws from a stream of its own (sim.seeding)."""
    family = get_task(task) if isinstance(task, str) else task
    return _sample(family, episode_rngs(seed), load_dr(dr), holdout)


def build_world(task: str | TaskFamily | None = None, seed: int = 0, dr: str | DRConfig = "off",
                fidelity: str = "full", variant: str = "ur5e") -> World:
    """The World alone, for callers that do not need the task instance."""
    return build_episode(task, seed, dr, fidelity, variant).world

