"""Templated success-check snippets per primitive, for the offline planner (and as the LLM's few-shot style).

Each snippet is plain sandbox code (`datagen.sandbox`), so template checks and language-model checks run
through the same path and judge episodes the same way. Thresholds follow the task families' predicates
(`sim.tasks`): a joint within 20 % of a limit counts as open/closed; "inside" is the sim's box-overlap
rule. A pick is judged by the gripper holding the object with its bottom clear of the table, so a grasp
that slips before lifting does not count.
"""

from __future__ import annotations

from datagen.plan import PlanError, SceneDescription, Subtask
from sim.scene import TABLE_TOP_Z
from sim.tasks.drawer import CLOSED_FRACTION, OPEN_FRACTION

LIFT_CLEARANCE = 0.03  # m between the object's lowest point and the table top for "lifted"


def snippet(condition: str) -> str:
    """Wrap one boolean expression as a check snippet."""
    return f"def check():\n    return {condition}\n"


def condition(primitive: str, args: dict, scene: SceneDescription) -> str:
    """The boolean expression that says the primitive achieved its goal."""
    if primitive == "pick":
        o = args["object"]
        return f"holding({o!r}) and aabb({o!r})[0][2] > {TABLE_TOP_Z + LIFT_CLEARANCE!r}"
    if primitive == "place":
        o, target = args["object"], args["target"]
        kind = "surface" if target == "table" else scene.by_name(target).kind
        relation = "on_top" if kind in ("object", "surface") else "inside"
        return f"{relation}({o!r}, {target!r}) and not holding({o!r})"
    if primitive == "open":
        return f"joint_fraction({args['joint']!r}) >= {OPEN_FRACTION!r}"
    if primitive == "close":
        return f"joint_fraction({args['joint']!r}) <= {CLOSED_FRACTION!r}"
    raise PlanError(f"no check template for primitive {primitive!r}")


def subtask_check(primitive: str, args: dict, scene: SceneDescription) -> str:
    return snippet(condition(primitive, args, scene))


def task_check(subtasks: tuple[Subtask, ...] | list[Subtask], scene: SceneDescription) -> str:
    """The whole task's check: the lasting effects of its subtasks, each object's and joint's last one.

    A pick is transient (it is undone by the place that follows), so it only counts when a plan ends with
    it; "put X in the drawer and close it" becomes inside(X, drawer) and not holding(X) and drawer closed.
    """
    last: dict[str, str] = {}
    for i, sub in enumerate(subtasks):
        key = sub.args.get("joint") or sub.args.get("object")
        if sub.primitive != "pick" or i == len(subtasks) - 1:
            last.pop(key, None)  # keep insertion order = order of the lasting effects
            last[key] = condition(sub.primitive, sub.args, scene)
    if not last:
        raise PlanError("a task check needs at least one subtask")
    return snippet(" and ".join(f"({c})" for c in last.values()) if len(last) > 1 else next(iter(last.values())))
