"""The task registry: one name per family; an unknown name lists the valid ones; the family an instruction
was phrased from."""

from __future__ import annotations

import re
from functools import lru_cache

from sim.tasks.base import TaskFamily
from sim.tasks.drawer import DrawerClose, DrawerOpen
from sim.tasks.drawer_put import PutInDrawer
from sim.tasks.drawer_stow import StowInOpenDrawer
from sim.tasks.pick_place import PickPlace
from sim.tasks.stack import Stack

TASKS: dict[str, TaskFamily] = {t.name: t for t in (PickPlace(), Stack(), DrawerOpen(), DrawerClose(), PutInDrawer(),
                                                  StowInOpenDrawer())}


def get_task(name: str) -> TaskFamily:
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; expected one of {sorted(TASKS)} "
                         f"(run `sudd sim tasks` to see them with example commands)") from None


def task_names() -> list[str]:
    return list(TASKS)


@lru_cache(maxsize=None)
def _phrasings() -> list[tuple[str, re.Pattern]]:
    """(family, the anchored pattern of one of its templates or paraphrases); a `{field}` matches any words."""
    out = []
    for name, t in TASKS.items():
        for phrase in (*t.templates, *t.paraphrases):
            parts = re.split(r"\{\w+\}", phrase)
            out.append((name, re.compile("^" + "(.+)".join(re.escape(p) for p in parts) + "$")))
    return out


def task_of_instruction(text: str) -> str | None:
    """The family whose templates (or unseen paraphrases) phrase `text`, or None when none does or several
    do (case, surrounding spaces and a final full stop aside)."""
    t = " ".join(str(text).lower().split()).rstrip(".!")
    found = {name for name, pattern in _phrasings() if pattern.match(t)}
    return found.pop() if len(found) == 1 else None
