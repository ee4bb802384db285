"""The task registry: one name per family; an unknown name lists the valid ones."""

from __future__ import annotations

from sim.tasks.base import TaskFamily
from sim.tasks.drawer import DrawerClose, DrawerOpen
from sim.tasks.drawer_put import PutInDrawer
from sim.tasks.pick_place import PickPlace
from sim.tasks.stack import Stack

TASKS: dict[str, TaskFamily] = {t.name: t for t in (PickPlace(), Stack(), DrawerOpen(), DrawerClose(), PutInDrawer())}


def get_task(name: str) -> TaskFamily:
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; expected one of {sorted(TASKS)} "
                         f"(run `sudd sim tasks` to see them with example commands)") from None


def task_names() -> list[str]:
    return list(TASKS)
