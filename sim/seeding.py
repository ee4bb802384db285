"""One episode seed, several independent random streams.

Each concern (object layout, visual DR, physics DR, sensor noise, policy sampling) draws from its own
stream spawned from `np.random.SeedSequence(seed)`. So turning one kind of randomization up or down never
shifts the numbers another kind sees: the same seed gives the same layout whatever the DR preset, and
the same textures whatever the physics ranges. The stream order below is part of the reproducibility
contract; add new streams at the end, never in between.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

STREAMS = ("layout", "visual", "physics", "sensor", "policy")


@dataclass(frozen=True)
class EpisodeRngs:
    """Named generators of one episode; each is a fresh, independent stream of `seed`."""

    seed: int
    layout: np.random.Generator  # task sampling: which objects, where, which colour shade
    visual: np.random.Generator  # textures, lights, camera poses
    physics: np.random.Generator  # friction, masses, damping, servo gains
    sensor: np.random.Generator  # camera noise / latency, joint-encoder noise
    policy: np.random.Generator  # anything the policy or oracle samples


def episode_rngs(seed: int) -> EpisodeRngs:
    """The streams of episode `seed` (a non-negative int); calling it twice gives identical streams."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"episode seed must be a non-negative integer, got {seed!r}")
    children = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
    gens = {name: np.random.default_rng(child) for name, child in zip(STREAMS, children)}
    return EpisodeRngs(seed=int(seed), **gens)


def parse_seeds(spec: str) -> tuple[int, ...]:
    """Seeds from "100003,100015,700000-700199" (ranges inclusive), or from a file of such items, one or more per
    line, `#` starting a comment. Order is kept and repeats dropped, so a list of failures can be re-run as is."""
    text = spec
    # A list is never read as a path: a long one is no valid file name (os.stat raised "File name too long").
    if not re.fullmatch(r"[\d,\-\s]*", spec) and _is_file(spec):
        text = "\n".join(line.split("#", 1)[0] for line in Path(spec).read_text().splitlines())
    seeds: list[int] = []
    for item in text.replace(",", " ").split():
        lo, sep, hi = item.partition("-")
        try:
            a, b = int(lo), int(hi if sep else lo)
        except ValueError:
            raise ValueError(f"seeds: {item!r} is not a seed or a range; expected non-negative integers like "
                             "100003 or 700000-700199, comma-separated, or a file of them") from None
        if a < 0 or b < a:
            raise ValueError(f"seeds: {item!r}: a range runs from a non-negative seed up to one at least as large")
        seeds.extend(range(a, b + 1))
    if not seeds:
        raise ValueError(f"seeds: {spec!r} names no seed; expected e.g. 100003,100015,700000-700199 or a file")
    return tuple(dict.fromkeys(seeds))


def _is_file(spec: str) -> bool:
    try:
        return Path(spec).is_file()
    except OSError:  # no name a file system takes (too long): then it is meant as a list, and parsed as one
        return False


def resolve_seeds(seeds: str | None, episodes: int | None, seed_offset: int | None,
                  default_episodes: int | None, default_offset: int) -> tuple[int, ...]:
    """The seeds a command line names: `--seeds LIST|FILE`, or `--episodes N` from `--seed-offset` (each falling
    back to its default; default_episodes None: the count must be given)."""
    if seeds is not None:
        if episodes is not None or seed_offset is not None:
            raise ValueError("--seeds names the episodes itself, not both: leave out --episodes and --seed-offset "
                             "with it")
        return parse_seeds(seeds)
    n = default_episodes if episodes is None else episodes
    if n is None:
        raise ValueError("give either --episodes N (seeds --seed-offset .. +N-1) or --seeds LIST|FILE")
    if n < 1:
        raise ValueError(f"--episodes {n}: expected at least 1 episode per task")
    offset = default_offset if seed_offset is None else seed_offset
    return tuple(range(offset, offset + n))


__all__ = ["EpisodeRngs", "episode_rngs", "parse_seeds", "resolve_seeds", "STREAMS"]
