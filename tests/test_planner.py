"""The offline planner: every template of every task family, paraphrases, reference resolution, clear errors,
and templated checks that run in the sandbox against real built episodes (and agree with the oracles)."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.checks import task_check
from datagen.plan import PlanError, SceneDescription, SceneObject, describe
from datagen.planner import LanguagePlanner, OfflinePlanner, UnknownTaskError, make_planner
from datagen.sandbox import compile_check, run_check
from sim.build import build_episode
from sim.dr_config import preset
from sim.state import StateView
from sim.tasks import TASKS

PLANNER = OfflinePlanner()
SLIDE = "cabinet/slide"


def template_fields(inst) -> dict:
    p, f = inst.params, {}
    if "target" in p:
        f["obj"] = inst.obj(p["target"]).phrase
    if "bin" in p:
        f["bin"] = p["bin"].removeprefix("bin_")
    if "top" in p:
        f["top"], f["bottom"] = inst.obj(p["top"]).phrase, inst.obj(p["bottom"]).phrase
    return f


def expected_steps(inst) -> list[tuple[str, str, dict]]:
    """(text, primitive, args) the plan must have, from the instance's ground truth."""
    p = inst.params
    if inst.family == "pick_place":
        o = inst.obj(p["target"])
        return [(f"pick up the {o.phrase}", "pick", {"object": o.name}),
                (f"put the {o.phrase} in the {p['bin'][4:]} bin", "place", {"object": o.name, "target": p["bin"]})]
    if inst.family == "stack":
        top, bottom = inst.obj(p["top"]), inst.obj(p["bottom"])
        return [(f"pick up the {top.phrase}", "pick", {"object": top.name}),
                (f"put the {top.phrase} on the {bottom.phrase}", "place", {"object": top.name, "target": bottom.name})]
    if inst.family == "drawer_open":
        return [("open the drawer", "open", {"joint": SLIDE})]
    if inst.family == "drawer_close":
        return [("close the drawer", "close", {"joint": SLIDE})]
    o = inst.obj(p["target"])
    if inst.family == "drawer_stow":  # the drawer is open already
        return [(f"pick up the {o.phrase}", "pick", {"object": o.name}),
                (f"put the {o.phrase} in the drawer", "place", {"object": o.name, "target": "cabinet"})]
    return [("open the drawer", "open", {"joint": SLIDE}), (f"pick up the {o.phrase}", "pick", {"object": o.name}),
            (f"put the {o.phrase} in the drawer", "place", {"object": o.name, "target": "cabinet"}),
            ("close the drawer", "close", {"joint": SLIDE})]


@pytest.mark.parametrize("family", list(TASKS))
def test_every_template_parses_for_sampled_instances(family):
    fam = TASKS[family]
    for seed in range(40):  # 5 families x 40 = 200 instances, every template each
        inst = fam.sample(np.random.default_rng(seed), preset("light"))
        scene = describe(inst)
        for text in {inst.instruction, *(t.format(**template_fields(inst)) for t in fam.templates)}:
            plan = PLANNER.plan(text, scene)
            plan.validate(scene)
            assert plan.planner == "offline" and plan.instruction == text
            assert [(s.text, s.primitive, s.args) for s in plan.subtasks] == expected_steps(inst), text
            for snippet in [s.check for s in plan.subtasks] + [plan.task_check]:
                compile_check(snippet, scene)


def _scene(drawer: bool = True) -> SceneDescription:
    objs = [SceneObject("obj0", "red block", "object"), SceneObject("obj1", "blue block", "object"),
            SceneObject("obj2", "green cylinder", "object"), SceneObject("obj3", "yellow bar", "object"),
            SceneObject("bin_left", "left bin", "container"), SceneObject("bin_middle", "middle bin", "container"),
            SceneObject("bin_right", "right bin", "container")]
    if drawer:
        objs.append(SceneObject("cabinet", "drawer", "articulated", joint=SLIDE))
    return SceneDescription(tuple(objs + [SceneObject("table", "table", "surface")]))


PICK0 = ("pick", {"object": "obj0"})
PARAPHRASES = [
    ("Put the red block in the left bin.", [PICK0, ("place", {"object": "obj0", "target": "bin_left"})]),
    ("please drop the red block into the right bin", [PICK0, ("place", {"object": "obj0", "target": "bin_right"})]),
    ("move the red one inside the middle bin", [PICK0, ("place", {"object": "obj0", "target": "bin_middle"})]),
    ("place the red cube in the bin on the left", [PICK0, ("place", {"object": "obj0", "target": "bin_left"})]),
    ("toss the red block into the leftmost bin", [PICK0, ("place", {"object": "obj0", "target": "bin_left"})]),
    ("put the yellow bar in the centre bin", [("pick", {"object": "obj3"}),
                                              ("place", {"object": "obj3", "target": "bin_middle"})]),
    ("pick up the green one and put it in the right bin", [("pick", {"object": "obj2"}),
                                                           ("place", {"object": "obj2", "target": "bin_right"})]),
    ("grab the cylinder, then drop it into the left bin", [("pick", {"object": "obj2"}),
                                                           ("place", {"object": "obj2", "target": "bin_left"})]),
    ("stack the red block on top of the blue block", [PICK0, ("place", {"object": "obj0", "target": "obj1"})]),
    ("Place the red block on the blue one", [PICK0, ("place", {"object": "obj0", "target": "obj1"})]),
    ("put the red block onto the blue block", [PICK0, ("place", {"object": "obj0", "target": "obj1"})]),
    ("put the red block on the table", [PICK0, ("place", {"object": "obj0", "target": "table"})]),
    ("open the drawer", [("open", {"joint": SLIDE})]),
    ("Pull open the drawer!", [("open", {"joint": SLIDE})]),
    ("pull the cabinet drawer open", [("open", {"joint": SLIDE})]),
    ("shut the drawer", [("close", {"joint": SLIDE})]),
    ("push the drawer closed", [("close", {"joint": SLIDE})]),
    ("close the cabinet drawer", [("close", {"joint": SLIDE})]),
    ("store the red block inside the drawer and then shut the drawer",
     [("open", {"joint": SLIDE}), PICK0, ("place", {"object": "obj0", "target": "cabinet"}),
      ("close", {"joint": SLIDE})]),
    ("put the blue block into the drawer, and close it",
     [("open", {"joint": SLIDE}), ("pick", {"object": "obj1"}), ("place", {"object": "obj1", "target": "cabinet"}),
      ("close", {"joint": SLIDE})]),
    ("put the red block in the drawer", [("open", {"joint": SLIDE}), PICK0,
                                         ("place", {"object": "obj0", "target": "cabinet"})]),
    ("pick up the red block", [PICK0]),
]


@pytest.mark.parametrize("text,steps", PARAPHRASES)
def test_paraphrases(text, steps):
    plan = PLANNER.plan(text, _scene())
    assert [(s.primitive, s.args) for s in plan.subtasks] == steps
    assert all(s.text and s.text == s.text.lower() for s in plan.subtasks)


def test_subtask_language_and_task_check_of_the_long_horizon_task():
    plan = PLANNER.plan("put the red block in the drawer and close it", _scene())
    assert [s.text for s in plan.subtasks] == ["open the drawer", "pick up the red block",
                                               "put the red block in the drawer", "close the drawer"]
    assert "inside('obj0', 'cabinet')" in plan.task_check and "<= 0.2" in plan.task_check
    assert ">= 0.8" not in plan.task_check and "holding('obj0') and" not in plan.task_check
    assert task_check(plan.subtasks, _scene()) == plan.task_check


@pytest.mark.parametrize("text,message", [
    ("put the block in the left bin", "ambiguous"),
    ("put the purple block in the left bin", "the scene has: ['red block', 'blue block'"),
    ("put the red block in the far bin", "nothing in the scene is called 'the far bin'"),
    ("stack the red block on the red block", "on itself"),
    ("put the red block in the open left bin", "the left bin is not something that opens"),
])
def test_unresolvable_references_are_plan_errors_naming_the_scene(text, message):
    with pytest.raises(PlanError, match=message.replace("[", r"\[")):
        PLANNER.plan(text, _scene())


def test_a_drawer_task_without_a_drawer_is_a_plan_error():
    with pytest.raises(PlanError, match="nothing in the scene is called 'the drawer'"):
        PLANNER.plan("open the drawer", _scene(drawer=False))


@pytest.mark.parametrize("text", ["dance a jig", "", "open the red block",
                                  "put the red block in the left bin and close it",
                                  "make me a sandwich and close the drawer", "close the drawer and open it"])
def test_unknown_language_lists_the_task_families(text):
    with pytest.raises(UnknownTaskError) as e:
        PLANNER.plan(text, _scene())
    for name in TASKS:
        assert name in str(e.value)
    assert "'put the red block in the left bin'" in str(e.value) and "'open the drawer'" in str(e.value)


def test_make_planner():
    assert isinstance(make_planner("offline"), OfflinePlanner)
    assert isinstance(make_planner(), LanguagePlanner)
    with pytest.raises(ValueError, match="unknown planner kind"):
        make_planner("oracle")
    with pytest.raises(ValueError, match="needs an endpoint and a model"):
        make_planner("llm", llm_url=None, llm_model=None)


@pytest.mark.parametrize("family", list(TASKS))
def test_checks_run_in_the_sandbox_on_built_episodes(family):
    for seed in (0, 1):
        ep = build_episode(family, seed, "off", "fast")
        scene, state = describe(ep.instance), StateView(ep.world)
        plan = PLANNER.plan(ep.instruction, scene)
        verdicts = [run_check(s.check, state, scene) for s in plan.subtasks]
        assert all(type(v) is bool for v in verdicts)
        # At the start nothing is done, except that drawer_put's drawer starts closed (its last step).
        assert verdicts[-1] is (family == "drawer_put")
        assert run_check(plan.task_check, state, scene) is False is ep.success()


@pytest.mark.parametrize("family", ["pick_place", "stack", "drawer_open"])
def test_template_checks_agree_with_the_oracle(family):
    ep = build_episode(family, 0, "off", "fast")
    scene, state = describe(ep.instance), StateView(ep.world)
    plan = PLANNER.plan(ep.instruction, scene)
    seen = [False] * len(plan.subtasks)
    steps = [0]

    def observe(world):
        steps[0] += 1
        if steps[0] % 50 == 0:
            for i, s in enumerate(plan.subtasks):
                seen[i] = seen[i] or run_check(s.check, state, scene)

    ep.task.oracle(ep.world, ep.instance, observer=observe)
    assert all(seen), [s.text for s, ok in zip(plan.subtasks, seen) if not ok]
    assert ep.success() and run_check(plan.task_check, state, scene)
