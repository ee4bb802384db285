"""Language planners: an instruction plus a scene description in, a validated `Plan` out.

`OfflinePlanner` is a deterministic parser of the task families' language (every template in `sim.tasks`
and common paraphrases), so data generation runs without a network and tests are exact. It resolves
"the red block" / "the red one" / "the left bin" / "the bin on the left" / "the drawer" to scene names
through the scene's own phrases, decomposes the task into primitive subtasks, and attaches the templated
checks from `datagen.checks`. `datagen.llm.LLMPlanner` does the same through a language model.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Protocol, runtime_checkable

from datagen.checks import subtask_check, task_check
from datagen.plan import Plan, PlanError, SceneDescription, SceneObject, Subtask
from sim.colors import COLOR_CLASSES

DEFAULT_CACHE_DIR = Path(os.environ.get("SUDD_CACHE", Path.home() / ".cache" / "sudd")) / "llm"

_VERB = r"(?:put|place|move|drop|set|stack|store|stow|toss|throw|transfer|insert|stick)"
_PREP = r"(?:inside of|inside|into|in to|in|onto|on to|on top of|on|to|over|atop)"
_PICK_THEN = r"(?:pick up|pick|grab|take|lift|get)\s+(?P<obj1>.+?)\s+(?:and|then|and then)\s+" + _VERB + r"\s+it"
_PLACE = re.compile(rf"^(?:{_PICK_THEN}|(?:pick up and\s+)?{_VERB}\s+(?P<obj2>.+?))\s+{_PREP}\s+(?P<dest>.+)$")
_CLOSE_AFTER = re.compile(r"^(?P<rest>.+?)\s+(?:and then|and|then)\s+(?:close|shut|push)\s+"
                          r"(?:it|the (?:cabinet )?drawer)(?:\s+(?:shut|closed|again|afterwards))?$")
_OPEN = re.compile(r"^(?:open|pull open|slide open|open up)\s+(?P<d>.+)$|^(?:pull|slide)\s+(?P<d2>.+?)\s+(?:open|out)$")
_CLOSE = re.compile(r"^(?:close|shut|push closed|push shut)\s+(?P<d>.+)$"
                    r"|^(?:push|slide)\s+(?P<d2>.+?)\s+(?:shut|closed|in)$")
_PICK = re.compile(r"^(?:pick up|pick|grab|lift|lift up)\s+(?P<obj>.+?)(?:\s+up)?$")
_OPEN_DEST = re.compile(r"^((?:the|a|an)\s+)?(?:open|opened)\s+")
_ARTICLE = re.compile(r"^(?:the|a|an)\s+")
_SYNONYMS = {"centre": "middle", "center": "middle", "cube": "block", "rod": "bar", "stick": "bar",
             "can": "cylinder", "sphere": "ball"}


class UnknownTaskError(PlanError):
    """Language the planner does not understand; the message lists the task families it knows."""


@runtime_checkable
class LanguagePlanner(Protocol):
    def plan(self, instruction: str, scene: SceneDescription) -> Plan: ...


def supported_tasks() -> str:
    """The task families with example phrasings, from the families' own templates (so they stay in sync)."""
    from sim.tasks import TASKS

    fields = {"obj": "red block", "bin": "left", "top": "red block", "bottom": "blue block"}
    lines = [f"  {name}: {fam.description} e.g. " + "; ".join(repr(t.format(**fields)) for t in fam.templates[:2])
             for name, fam in TASKS.items()]
    return "supported task families:\n" + "\n".join(lines)


def normalize(text: str) -> str:
    text = re.sub(r"[,.;:!?]", " ", text.lower())
    text = re.sub(r"^(?:please|robot|now)\s+|\s+(?:please|for me)$", "", re.sub(r"\s+", " ", text).strip())
    return re.sub(r"\s+", " ", text).strip()


class OfflinePlanner:
    """Deterministic parser for the task families' language; raises UnknownTaskError on anything else."""

    name = "offline"

    def plan(self, instruction: str, scene: SceneDescription) -> Plan:
        text = normalize(instruction)
        close_after = False
        m = _CLOSE_AFTER.match(text)
        if m and not _CLOSE.match(text):
            text, close_after = m.group("rest"), True
        subtasks = self._decompose(text, instruction, scene, close_after)
        plan = Plan(instruction, tuple(subtasks), self.name, task_check(subtasks, scene))
        return plan.validate(scene)

    def _decompose(self, text: str, instruction: str, scene: SceneDescription, close_after: bool) -> list[Subtask]:
        if m := _OPEN.match(text):
            if not close_after:
                return [_open(_drawer(m.group("d") or m.group("d2"), scene, instruction), scene)]
        elif m := _CLOSE.match(text):
            if not close_after:
                return [_close(_drawer(m.group("d") or m.group("d2"), scene, instruction), scene)]
        elif m := _PLACE.match(text):
            obj = resolve(m.group("obj1") or m.group("obj2"), scene, kinds=("object",))
            # "the open drawer" says the drawer is open already: no opening step (drawer_stow)
            dest_phrase, already_open = _OPEN_DEST.subn(r"\1", m.group("dest"))
            dest = resolve(dest_phrase, scene, kinds=("container", "articulated", "object", "surface"))
            if already_open and dest.kind != "articulated":
                raise PlanError(f"{instruction!r}: the {dest.phrase} is not something that opens")
            if dest.name == obj.name:
                raise PlanError(f"{instruction!r}: cannot put the {obj.phrase} on itself")
            if dest.kind == "articulated":
                steps = ([] if already_open else [_open(dest, scene)]) + [_pick(obj, scene), _place(obj, dest, scene)]
                return steps + ([_close(dest, scene)] if close_after else [])
            if not close_after:
                return [_pick(obj, scene), _place(obj, dest, scene)]
        elif m := _PICK.match(text):
            if not close_after:
                return [_pick(resolve(m.group("obj"), scene, kinds=("object",)), scene)]
        raise UnknownTaskError(f"cannot parse the instruction {instruction!r}; {supported_tasks()}")


def resolve(phrase: str, scene: SceneDescription, kinds: tuple[str, ...]) -> SceneObject:
    """A noun phrase to the one scene object it names: exact phrase, "bin on the left", colour or shape alone."""
    words = [_SYNONYMS.get(w, w) for w in _ARTICLE.sub("", phrase.strip()).split()]
    text = " ".join(w for w in words if w not in ("one", "object", "thing", "piece"))
    text = re.sub(r"^(\w+)most\b", r"\1", re.sub(r"^bin (?:on|at) the (\w+)(?: side)?$", r"\1 bin", text))
    text = re.sub(r"^(?:cabinet|cabinet's|kitchen)\s+drawer$|^cabinet$", "drawer", text)
    candidates = [o for o in scene.objects if o.kind in kinds]
    for match in (lambda o: o.phrase == text,  # "red block", "left bin", "drawer"
                  lambda o: text in COLOR_CLASSES and o.kind == "object" and o.phrase.split()[0] == text,
                  lambda o: o.kind == "object" and o.phrase.split()[-1] == text,  # a shape that is unique
                  lambda o: text == f"{o.phrase.split()[0]} {o.kind}" or o.name == text):  # "left container"
        found = [o for o in candidates if match(o)]
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise PlanError(f"{phrase!r} is ambiguous: it could be {[o.phrase for o in found]}")
    known = [o.phrase for o in candidates]
    raise PlanError(f"nothing in the scene is called {phrase!r}; the scene has: {known}")


def _drawer(phrase: str, scene: SceneDescription, instruction: str) -> SceneObject:
    try:
        return resolve(phrase, scene, kinds=("articulated",))
    except PlanError as e:
        if not re.fullmatch(r"(?:the )?(?:cabinet |cabinet's |kitchen )?(?:drawer|cabinet)", phrase):
            raise UnknownTaskError(f"cannot parse the instruction {instruction!r}; {supported_tasks()}") from None
        raise e


def _pick(o: SceneObject, scene) -> Subtask:
    args = {"object": o.name}
    return Subtask(f"pick up the {o.phrase}", "pick", args, subtask_check("pick", args, scene))


def _place(o: SceneObject, dest: SceneObject, scene) -> Subtask:
    args = {"object": o.name, "target": dest.name}
    prep = "on" if dest.kind in ("object", "surface") else "in"
    return Subtask(f"put the {o.phrase} {prep} the {dest.phrase}", "place", args, subtask_check("place", args, scene))


def _open(d: SceneObject, scene) -> Subtask:
    args = {"joint": d.joint}
    return Subtask(f"open the {d.phrase}", "open", args, subtask_check("open", args, scene))


def _close(d: SceneObject, scene) -> Subtask:
    args = {"joint": d.joint}
    return Subtask(f"close the {d.phrase}", "close", args, subtask_check("close", args, scene))


def make_planner(kind: str = "offline", llm_url: str | None = None, llm_model: str | None = None,
                 cache_dir: str | Path | None = None, **llm_options) -> LanguagePlanner:
    """The planner by name; the LLM one reads `SUDD_LLM_URL` / `SUDD_LLM_MODEL` when not given them."""
    if kind == "offline":
        return OfflinePlanner()
    if kind == "llm":
        from datagen.llm import LLMPlanner

        url, model = llm_url or os.environ.get("SUDD_LLM_URL"), llm_model or os.environ.get("SUDD_LLM_MODEL")
        if not url or not model:
            raise ValueError("the llm planner needs an endpoint and a model: pass llm_url/llm_model "
                             "(or set SUDD_LLM_URL / SUDD_LLM_MODEL), e.g. http://localhost:8000/v1 and a model name")
        return LLMPlanner(url, model, cache_dir=cache_dir or DEFAULT_CACHE_DIR, **llm_options)
    raise ValueError(f"unknown planner kind {kind!r}; expected 'offline' or 'llm'")
