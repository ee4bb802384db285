"""Which task families a bundle runs as their phases by default: the manifest's `phased` list.

Why a bundle records it: whether a long command is better played as the skills it is made of (runtime/phases.py)
is measured on the bundle, as its pace is. The shipped bundle completes drawer_put run as its phases and never as
one command (policy/EXPERIMENTS.md, "drawer_put's object from the start"), so `sudd run` and `sudd eval` follow
the bundle's list unless told `--phases` (every family that has phases) or `--no-phases` (none).

PHASED is the phase table: family -> (text or None for the command itself, the family whose pace the phase
plays at), one entry per count of grasp cycles completed.
"""

from __future__ import annotations

from typing import Iterable

PHASED: dict[str, tuple[tuple[str | None, str], ...]] = {
    "drawer_put": (("open the drawer", "drawer_open"), (None, "drawer_put"), ("close the drawer", "drawer_close")),
}


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
