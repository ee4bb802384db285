"""Which task families a bundle runs as their phases by default: the manifest's `phased` list.

Why a bundle records it: whether a long command is better played as the skills it is made of (runtime/phases.py)
is measured on the bundle, as its pace is. The shipped bundle completes drawer_put run as its phases and never as
one command (policy/EXPERIMENTS.md, "drawer_put's object from the start"), so `sudd run` and `sudd eval` follow
the bundle's list unless told `--phases` (every family that has phases) or `--no-phases` (none).

PHASED is the phase table: family -> (text or None for the command itself, the family whose pace the phase
plays at), one entry per count of grasp cycles completed.
"""

from __future__ import annotations

import re
from typing import Iterable

PHASED: dict[str, tuple[tuple[str | None, str], ...]] = {
    "drawer_put": (("open the drawer", "drawer_open"), (None, "drawer_put"), ("close the drawer", "drawer_close")),
}

# A phase that runs the command's own family (text None above) under a text of its own, "{obj}" filled from the
# command, for a bundle taught it (`sudd cut-phases --phase drawer_put:1`; `own_texts_taught`). Why: drawer_put's
# middle cycle starts where drawer_close's data does (the drawer open, the fingers at its handle, objects on the
# table), and the images must then tell the two apart: the command's MiniLM embedding is 0.78 from "close the
# drawer", this text's 0.63. A bundle never taught it runs the phase under the command, as before. Measured on
# step 28 (policy/EXPERIMENTS.md, "drawer_put's middle cycle under a text of its own"): the text did not keep the
# arm off the handle (12 of 40 against 18 of 40), so no shipped bundle is taught it.
OWN_PHASE_TEXT: dict[str, dict[int, str]] = {
    "drawer_put": {1: "pick up the {obj} and put it in the open drawer"},
}

# A phase of the command's own family that another family's skill does, for a bundle taught that family (its
# `tasks`): family -> {phase: skill family}. The phase runs under OWN_PHASE_TEXT (a template of the skill's
# family) after the arm has gone back to where the command started (runtime/retreat.py), where that family's data
# starts. Why: drawer_put's middle cycle started at the handle just let go looks like the start of the closing
# cycle; from the start pose, an open drawer and an object on the table are a start the text tells apart, as it
# tells every other family's (sim/tasks/drawer_stow.py).
SKILL_PHASE: dict[str, dict[int, str]] = {
    "drawer_put": {1: "drawer_stow"},
}

# The object a drawer_put command names: the phrase after its first article, up to "in/inside/into the drawer"
# (every template and paraphrase of sim/tasks/drawer_put.py, and the likes of "stow a red block into the drawer").
_DRAWER_OBJECT = re.compile(r"\b(?:the|a|an)\s+(.+?)\s+(?:in|inside|into)\s+(?:the|a)\s+drawer\b", re.IGNORECASE)


def command_object(command: str) -> str | None:
    """The object phrase of a drawer command ("put the red block in the drawer and close it" -> "red block")."""
    m = _DRAWER_OBJECT.search(command or "")
    return " ".join(m.group(1).split()) if m else None


def fill_object(template: str, command: str) -> str | None:
    """`template` with the command's object in place of "{obj}", or None where the command names none."""
    obj = command_object(command)
    return template.format(obj=obj) if obj else None


def own_phase_text(family: str, phase: int, command: str) -> str | None:
    """Phase `phase` of `family`'s own text for `command`, or None (no such text, or no object in the command)."""
    template = OWN_PHASE_TEXT.get(family, {}).get(phase)
    return fill_object(template, command) if template else None


def _template_pattern(template: str) -> re.Pattern:
    return re.compile(re.escape(template).replace(re.escape("{obj}"), ".+"), re.IGNORECASE)


def own_texts_taught(family: str, instructions: Iterable[str]) -> bool:
    """Whether a bundle's trained instructions hold one of `family`'s own phase texts (for any object): only
    then does it run those phases under them."""
    patterns = [_template_pattern(t) for t in OWN_PHASE_TEXT.get(family, {}).values()]
    return any(p.fullmatch(text) for p in patterns for text in instructions)


def check_phased(families, known: Iterable[str], where: str) -> tuple[str, ...]:
    """A validated tuple of phased families; errors name `where` and what is allowed."""
    if not isinstance(families, (list, tuple)) or not all(isinstance(f, str) for f in families):
        raise ValueError(f"{where}: expected a list of task family names, got {families!r}")
    known = set(known)
    for f in families:
        if f not in PHASED:
            raise ValueError(f"{where}: {f!r} has no phases; families with phases: {', '.join(sorted(PHASED))}")
        if known and f not in known:
            raise ValueError(f"{where}: {f!r} is not one of the bundle's task families {sorted(known)}")
    return tuple(dict.fromkeys(families))


def bundle_phased(manifest: dict) -> tuple[str, ...]:
    """The manifest's `phased` (bundles before it: none)."""
    return check_phased(manifest.get("phased", []), manifest.get("tasks") or [], "manifest phased")


def resolve_phased(bundle_families: tuple[str, ...], choice: bool | None) -> tuple[str, ...]:
    """The families run as phases: the bundle's (choice None), every family with phases (True), none (False)."""
    if choice is None:
        return tuple(bundle_families)
    return tuple(PHASED) if choice else ()
