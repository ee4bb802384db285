"""Task families: scene setup from a seed, language, success predicate, scripted oracle."""

from sim.tasks.base import Holdout, TaskFamily, TaskInstance
from sim.tasks.registry import TASKS, get_task, task_names, task_of_instruction

__all__ = ["Holdout", "TaskFamily", "TaskInstance", "TASKS", "get_task", "task_names", "task_of_instruction"]
