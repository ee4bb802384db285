"""The language planner's vocabulary: a scene description in, a plan of subtasks out.

A planner (offline parser or LLM) sees only the scene's description: the objects' names and the phrases a
person would use for them. It answers with subtasks, each one primitive call plus a success-check snippet
written against the sandboxed state API (`datagen.sandbox`). Planning never touches the simulator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

# The primitives a subtask may call, with the arguments each takes (all are scene names).
PRIMITIVES: dict[str, tuple[str, ...]] = {
    "pick": ("object",),  # grasp a free object and lift it
    "place": ("object", "target"),  # put the held object in/on a target: a bin, the drawer, another object, "table"
    "open": ("joint",),  # grasp the part's handle and move the joint to its open limit
    "close": ("joint",),  # move the joint to its closed limit
}


class PlanError(ValueError):
    """A plan that cannot be executed: unknown primitive, missing or unknown argument, empty plan."""


@dataclass(frozen=True)
class SceneObject:
    """One thing the planner may refer to."""

    name: str  # scene name, e.g. "obj0", "bin_left", "cabinet"
    phrase: str  # what a person calls it, e.g. "red block", "left bin", "drawer"
    kind: str  # "object" (free, graspable), "container" (bin), "articulated" (has `joint`), "surface"
    joint: str = ""  # for articulated parts: the joint moved by open/close, e.g. "cabinet/slide"


@dataclass(frozen=True)
class SceneDescription:
    objects: tuple[SceneObject, ...]

    def names(self) -> list[str]:
        return [o.name for o in self.objects]

    def by_name(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise PlanError(f"no object named {name!r} in the scene; known: {self.names()}")

    def joints(self) -> list[str]:
        return [o.joint for o in self.objects if o.joint]

    def prompt_lines(self) -> list[str]:
        """How the scene is shown to a language model: one line per object."""
        return [f"- {o.name}: {o.phrase} ({o.kind}{', joint ' + o.joint if o.joint else ''})" for o in self.objects]


@dataclass(frozen=True)
class Subtask:
    text: str  # the subtask's language label, e.g. "pick up the red block"
    primitive: str
    args: dict = field(default_factory=dict)
    check: str = ""  # success-check snippet: defines `def check(): return <bool>`

    def validate(self, scene: SceneDescription) -> None:
        if self.primitive not in PRIMITIVES:
            raise PlanError(f"subtask {self.text!r}: unknown primitive {self.primitive!r}; "
                            f"expected one of {sorted(PRIMITIVES)}")
        wanted = PRIMITIVES[self.primitive]
        if set(self.args) != set(wanted):
            raise PlanError(f"subtask {self.text!r}: primitive {self.primitive!r} takes arguments {list(wanted)}, "
                            f"got {sorted(self.args)}")
        for key, value in self.args.items():
            if not isinstance(value, str):
                raise PlanError(f"subtask {self.text!r}: argument {key!r} must be a scene name, got {value!r}")
            if key == "joint":
                if value not in scene.joints():
                    raise PlanError(f"subtask {self.text!r}: unknown joint {value!r}; known: {scene.joints()}")
            elif value != "table":
                scene.by_name(value)
        if not self.text.strip():
            raise PlanError("a subtask needs a language label")


@dataclass(frozen=True)
class Plan:
    instruction: str
    subtasks: tuple[Subtask, ...]
    planner: str  # "offline" or "llm:<model>"
    task_check: str = ""  # snippet for the whole task (the root task's success), when the planner wrote one

    def validate(self, scene: SceneDescription) -> "Plan":
        if not self.subtasks:
            raise PlanError(f"empty plan for {self.instruction!r}")
        for sub in self.subtasks:
            sub.validate(scene)
        return self

    def record(self) -> dict:
        return asdict(self)


def describe(instance) -> SceneDescription:
    """The planner's view of a sim TaskInstance: task objects, bins, the drawer."""
    objs: list[SceneObject] = [SceneObject(o.name, o.phrase, "object") for o in instance.objects]
    for name, _x in instance.params.get("bins", []):
        objs.append(SceneObject(f"bin_{name}", f"{name} bin", "container"))
    if "cabinet" in instance.params:
        objs.append(SceneObject("cabinet", "drawer", "articulated", joint="cabinet/slide"))
    objs.append(SceneObject("table", "table", "surface"))
    return SceneDescription(tuple(objs))
