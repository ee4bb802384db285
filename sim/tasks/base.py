"""What a task family is: scene setup from a seed, language, a success predicate and a scripted oracle.

A family samples a `TaskInstance` (every random choice made, JSON-able) from an rng; the instance builds
its objects into a scene spec and is judged by the family's `success(state, instance)`. The oracle solves it
with privileged state; it checks that tasks are solvable and serves tests, not data generation.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import ClassVar

import mujoco
import numpy as np

from sim import objects as obj
from sim.colors import COLOR_CLASSES, sample_rgba
from sim.config import ConfigError, spec
from sim.dr_config import DRConfig
from sim.objects import Placement
from sim.scene import TASK_AREA

SHAPES = ("block", "cylinder", "bar")
# Shapes no training scene ever holds: the held-out shape suite's targets (split "eval_heldout_shape"). Kept out
# of SHAPES so that adding one changes no seed's scene. The ball is 6.4 cm across (5.4-7.4 under heavy DR's size
# scale): a sphere is held only at its equator, and on one under 5.2 cm across that lies lower than the safety
# layer lets the fingertips go over the table (the collector finds no grasp).
NOVEL_SHAPES = ("ball",)
OBJECT_COLORS = ("red", "orange", "yellow", "green", "blue", "purple", "pink", "white")
_SHAPE_SIZE = {"block": (0.022, 0.022, 0.022), "cylinder": (0.022, 0.024), "bar": (0.045, 0.018, 0.018),
               "ball": (0.032,)}
SPLITS = ("train", "eval_heldout", "eval_heldout_shape")


@dataclass(frozen=True)
class Holdout:
    """Colours/shapes kept out of training. `split="eval_heldout"` makes the task's target use only them;
    `"eval_heldout_shape"` gives it a held-out shape (NOVEL_SHAPES are allowed then) in a colour the data had."""

    colors: tuple[str, ...] = field(default=(), metadata=spec(choices=tuple(COLOR_CLASSES)))
    shapes: tuple[str, ...] = field(default=(), metadata=spec(choices=SHAPES + NOVEL_SHAPES))
    split: str = field(default="train", metadata=spec(choices=SPLITS))

    def allowed(self, pool: tuple[str, ...], held: tuple[str, ...], for_target: bool) -> tuple[str, ...]:
        if self.split != "train" and for_target and held:
            out = tuple(p for p in pool if p in held)
            if not out:
                raise ConfigError(f"held-out {list(held)}: none of them can be this task's target (it takes "
                                  f"{list(pool)})")
            return out
        out = tuple(p for p in pool if p not in held)
        if not out:
            raise ConfigError(f"holdout leaves no choice among {list(pool)}; hold out fewer")
        return out


@dataclass(frozen=True)
class ObjectSpec:
    """One movable object: its name in the scene, what the language calls it, and its geometry."""

    name: str
    shape: str
    color: str
    size: tuple[float, ...]
    rgba: tuple[float, ...]
    placement: Placement

    @property
    def phrase(self) -> str:
        return f"{self.color} {self.shape}"

    def build(self, spec: mujoco.MjSpec) -> None:
        if self.shape == "cylinder":
            obj.add_cylinder(spec, self.name, self.size[0], self.size[1], self.rgba, self.placement)
        elif self.shape == "ball":
            obj.add_sphere(spec, self.name, self.size[0], self.rgba, self.placement)
        else:
            obj.add_block(spec, self.name, self.size, self.rgba, self.placement)

    @property
    def half_height(self) -> float:
        return {"cylinder": self.size[1], "ball": self.size[0]}.get(self.shape, self.size[-1])


@dataclass
class TaskInstance:
    """One sampled task: what to say, which objects, and the family-specific parameters."""

    family: str
    instruction: str
    objects: list[ObjectSpec]
    params: dict
    seed: int = 0

    def obj(self, name: str) -> ObjectSpec:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(name)

    def record(self) -> dict:
        return {"family": self.family, "instruction": self.instruction, "params": self.params, "seed": self.seed,
                "objects": [asdict(o) for o in self.objects]}


class TaskFamily:
    """Base class: subclasses set the class attributes and implement sample/build/success/oracle."""

    name: ClassVar[str]
    description: ClassVar[str]
    templates: ClassVar[tuple[str, ...]]  # language templates; `{...}` fields filled by `sample`
    # Phrasings never used to generate data: the evaluation's unseen-command test (same `{...}` fields).
    paraphrases: ClassVar[tuple[str, ...]] = ()
    max_seconds: ClassVar[float] = 30.0  # a generous episode time limit for oracles and policies
    # The never-trained shapes its target may take in the held-out shape suite (stack: none, a ball on a block
    # is no stack).
    novel_shapes: ClassVar[tuple[str, ...]] = NOVEL_SHAPES

    def sample(self, rng: np.random.Generator, dr: DRConfig, holdout: Holdout = Holdout()) -> TaskInstance:
        raise NotImplementedError

    def build(self, spec: mujoco.MjSpec, inst: TaskInstance) -> None:
        for o in inst.objects:
            o.build(spec)

    def initialize(self, world, inst: TaskInstance) -> None:
        """Set the task's initial joint states after compile (e.g. a drawer left open)."""

    def success(self, state, inst: TaskInstance) -> bool:
        raise NotImplementedError

    def oracle(self, world, inst: TaskInstance, observer=None) -> None:
        """Solve the task with privileged state; `observer(world)` is called after every physics step."""
        raise NotImplementedError

    def example(self) -> str:
        inst = self.sample(np.random.default_rng(0), DRConfig())
        return inst.instruction

    def phrase(self, rng: np.random.Generator, **fields) -> str:
        return str(rng.choice(self.templates)).format(**fields)

    def fields(self, inst: TaskInstance) -> dict[str, str]:
        """The template fields of an instance (what `sample` filled in)."""
        return {}

    def paraphrase(self, inst: TaskInstance, rng: np.random.Generator) -> str:
        """The instance's command in a phrasing the data never used."""
        if not self.paraphrases:
            raise ValueError(f"task family {self.name} has no paraphrases")
        return str(rng.choice(self.paraphrases)).format(**self.fields(inst))


def sample_objects(rng: np.random.Generator, dr: DRConfig, holdout: Holdout, count: int, slots: list[Placement],
                   target_shapes: tuple[str, ...] = SHAPES, prefix: str = "obj",
                   novel_shapes: tuple[str, ...] = NOVEL_SHAPES) -> list[ObjectSpec]:
    """`count` objects with distinct (colour, shape) phrases; the first is the task's target, in the held-out
    shape split one of `novel_shapes` (those held out) in a colour the data had."""
    novel = holdout.split == "eval_heldout_shape"
    chosen: list[ObjectSpec] = []
    used: set[tuple[str, str]] = set()
    for i in range(count):
        target = i == 0
        pool = (target_shapes + (novel_shapes if novel else ())) if target else SHAPES
        shapes = holdout.allowed(pool, holdout.shapes, target)
        colors = holdout.allowed(OBJECT_COLORS, holdout.colors, target and not novel)
        for _ in range(100):
            shape, color = str(rng.choice(shapes)), str(rng.choice(colors))
            if (shape, color) not in used and all(c.color != color for c in chosen):
                break
        used.add((shape, color))
        scale = rng.uniform(*dr.objects.size_scale)
        size = tuple(float(s * scale) for s in _SHAPE_SIZE[shape])
        rgba = tuple(sample_rgba(color, rng, dr.visual.object_color_spread))
        chosen.append(ObjectSpec(f"{prefix}{i}", shape, color, size, rgba, slots[i]))
    return chosen


def sample_slots(rng: np.random.Generator, dr: DRConfig, count: int, region=None, min_gap: float = 0.09,
                 keep_out: list[tuple[float, float, float]] = ()) -> list[Placement]:
    """Non-overlapping placements in `region` ((x0, x1), (y0, y1)); nominal grid + DR jitter, no overlaps.

    `keep_out` is a list of (x, y, radius) discs to avoid (bins, the cabinet).
    """
    (x0, x1), (y0, y1) = region or TASK_AREA
    # Nominal slots on a grid; DR jitters them (xy_jitter) and spins the objects (yaw_jitter).
    nx = max(2, int((x1 - x0) / min_gap))
    ny = max(1, int((y1 - y0) / min_gap))
    grid = [(x0 + (i + 0.5) * (x1 - x0) / nx, y0 + (j + 0.5) * (y1 - y0) / ny) for i in range(nx) for j in range(ny)]
    jitter = dr.objects.xy_jitter
    for attempt in range(_LAYOUT_ATTEMPTS):
        # Later attempts shrink the jitter: a crowded region still gets a layout, and the first attempt's
        # draws (which most seeds use) never change.
        out = _try_slots(rng, dr, grid, count, (x0, x1, y0, y1), min_gap, keep_out,
                         jitter * (1.0 - attempt / _LAYOUT_ATTEMPTS))
        if out is not None:
            return out
    raise RuntimeError(f"could not place {count} objects without overlap in region {region}; use fewer objects")


_LAYOUT_ATTEMPTS = 20


def _try_slots(rng, dr, grid, count, bounds, min_gap, keep_out, jitter) -> list[Placement] | None:
    x0, x1, y0, y1 = bounds
    order = rng.permutation(len(grid))
    out: list[Placement] = []
    for k in order:
        if len(out) == count:
            break
        gx, gy = grid[k]
        x = float(np.clip(gx + rng.uniform(-jitter, jitter), x0, x1))
        y = float(np.clip(gy + rng.uniform(-jitter, jitter), y0, y1))
        if any(np.hypot(x - p.x, y - p.y) < min_gap for p in out):
            continue
        if any(np.hypot(x - kx, y - ky) < kr for kx, ky, kr in keep_out):
            continue
        yaw = float(rng.uniform(-dr.objects.yaw_jitter, dr.objects.yaw_jitter))
        out.append(Placement(x, y, yaw))
    return out if len(out) == count else None
