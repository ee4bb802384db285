"""The goal query: where the object a command puts something on is, asked of the policy's own aux head as the
object it would grasp if the roles were swapped.

Why: a policy conditioned on its head's grasp and release points (aux_condition) finds the block it is told to
pick up (stack: 3.6 cm off on an episode's first frames) but not the block to put it on (10.2 cm off on the same
frames; 8-14 cm while carrying): MiniLM mean-pools the sentence, so the roles of "the red block" and "the blue
block" are barely in it, and the goal clause alone has not taught the head the second block. Asked "stack the
blue block on the red block" about the same first frames, the head's grasp point is the blue block, 3.5 cm off
the release point once a fixed offset (the release's height over the grasp) is added. In closed loop on the seen
seeds 100000-100019 the shipped bundle stacks 1/20 with its head's release point and 8/20 with this one (the
sim's true point gave an earlier run 10/20; policy/EXPERIMENTS.md, "The goal query").

How: per command of a family the bundle's manifest lists (`goal_query`), `role_swap` exchanges the object phrase
before the goal clause with the one in it; for the first `ticks` inferences the head reads the swapped sentence
(obs_encoder.onnx with its release flag off, or the bundle's goal locator, policy/goal_locator.py, where it has
one), and the median of its grasp points, in the base frame, plus `offset_m` is held for the rest of the command
and given to every inference as the release point (`Bundle.act(release=...)`): the object is on the table at rest
at the start, and later frames (the arm over it, an object in the fingers) are not scenes the swapped sentence was
trained on (measured: 13 cm off while carrying).

Torch-free: the runtime's policy node and `sudd eval` use it through the bundle. The offset is measured when the
bundle is exported (policy/goal_query_measure.py) and recorded with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.instruction import goal_clause

ARTICLES = ("the", "a", "an")
MAX_OFFSET_M = 0.3  # an offset further than this from the grasp point is no "height over it": a bad measurement
MAX_TICKS = 20
MAX_LOOK_M = 0.3  # per axis: a look pose further from home than this is no glance from the start


def check_xyz(values, where: str, limit: float, meaning: str) -> tuple[float, float, float]:
    """An offset (dx, dy, dz) in metres checked: 3 finite numbers, each within `limit`; a ValueError names `where`
    and says what the offset is (`meaning`, e.g. "from the start pose")."""
    ok = (isinstance(values, (list, tuple)) and len(values) == 3
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
          and bool(np.all(np.isfinite(values))) and max(abs(float(v)) for v in values) <= limit)
    if not ok:
        raise ValueError(f"{where} {values!r}: expected 3 finite numbers dx, dy, dz in metres {meaning}, "
                         f"each within {limit} m")
    return tuple(float(v) for v in values)


def parse_xyz(text: str, option: str, limit: float, meaning: str, example: str) -> tuple[float, float, float]:
    """"DX,DY,DZ" (metres) given to `option` -> a checked offset (check_xyz)."""
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise ValueError(f"{option} {text!r}: expected three numbers DX,DY,DZ in metres, e.g. {example}") from None
    return check_xyz(values, option, limit, meaning)


def check_look(look, where: str = "look") -> tuple[float, float, float]:
    """A look offset (dx, dy, dz) from the start pose's TCP, base frame [m], checked (check_xyz)."""
    return check_xyz(look, where, MAX_LOOK_M, "from the start pose")


def parse_look(text: str) -> tuple[float, float, float]:
    """"DX,DY,DZ" (metres) -> a checked look offset (check_look)."""
    return parse_xyz(text, "--look", MAX_LOOK_M, "from the start pose", "0.15,0.08,0.1")


def _phrase_after_article(words: list[str]) -> int | None:
    """Index of the first word after the last article in `words`, or None."""
    for i in range(len(words) - 1, -1, -1):
        if words[i].lower() in ARTICLES:
            return i + 1 if i + 1 < len(words) else None
    return None


def role_swap(text: str) -> str | None:
    """The command with its two object phrases exchanged ("put the red block on top of the blue block" -> "put
    the blue block on top of the red block"), or None where it does not name two: no goal clause, or no object
    phrase before it that ends in the goal's noun (the goal's last word; "set the red block down on the blue
    block" keeps "down" where it is)."""
    clause = goal_clause(text)
    if clause is None:
        return None
    words = text.strip().split()
    cw = clause.split()
    head = words[:len(words) - len(cw)]
    g = _phrase_after_article(cw)
    x0 = _phrase_after_article(head)
    if g is None or x0 is None:
        return None
    goal = cw[g:]
    noun = goal[-1].lower().strip(",.;!?")
    ends = [i for i in range(x0, len(head)) if head[i].lower().strip(",.;!?") == noun]
    if not ends:
        return None
    x1 = ends[0] + 1
    obj = head[x0:x1]
    swapped = head[:x0] + goal + head[x1:] + cw[:g] + obj
    return " ".join(swapped)


@dataclass(frozen=True)
class GoalQuerySpec:
    """The manifest's `goal_query`: which families use it, the offset from the swapped grasp point to the
    release point (base frame, metres) and for how many first inferences the head is asked."""

    families: tuple[str, ...]
    offset_m: tuple[float, float, float]
    ticks: int
    locator: bool = False  # asked of goal_locator.onnx (policy/goal_locator.py) instead of the obs encoder's head
    look_m: tuple[float, float, float] | None = None  # asked from the start pose moved this far (runtime/look.py)


def query_table(manifest: dict, key: str, needs: str, point: str) -> dict | None:
    """A manifest's query table `key` (goal_query, object_query) with its families checked: None where it has
    none; a ValueError where it is no table, the obs encoder lacks the input `needs` it gives the `point` through,
    or its families are not a non-empty list of the bundle's."""
    q = manifest.get(key)
    if q is None:
        return None
    if not isinstance(q, dict):
        raise ValueError(f"manifest {key}: expected a table, got {type(q).__name__}")
    if not manifest.get(needs, False):
        raise ValueError(f"manifest {key} needs {needs} true: the obs encoder must take the {point}")
    families, known = q.get("families"), set(manifest.get("tasks") or [])
    if not isinstance(families, list) or not families or not all(isinstance(f, str) and f in known for f in families):
        raise ValueError(f"manifest {key}.families {families!r}: expected a non-empty list of the bundle's "
                         f"task families {sorted(known)}")
    return q


def goal_query_spec(manifest: dict) -> GoalQuerySpec | None:
    """The validated `goal_query` of a manifest, None where it has none; a ValueError names the field."""
    q = query_table(manifest, "goal_query", "release_input", "release point")
    if q is None:
        return None
    families = q["families"]
    off = q.get("offset_m")
    ok = (isinstance(off, list) and len(off) == 3 and all(isinstance(v, (int, float)) for v in off)
          and np.all(np.isfinite(off)) and float(np.linalg.norm(off)) <= MAX_OFFSET_M)
    if not ok:
        raise ValueError(f"manifest goal_query.offset_m {off!r}: expected 3 finite numbers (metres), at most "
                         f"{MAX_OFFSET_M} m long")
    ticks = q.get("ticks")
    if not (isinstance(ticks, int) and 1 <= ticks <= MAX_TICKS):
        raise ValueError(f"manifest goal_query.ticks {ticks!r}: expected an integer in [1, {MAX_TICKS}]")
    locator = q.get("locator", False)
    if not isinstance(locator, bool):
        raise ValueError(f"manifest goal_query.locator {locator!r}: expected true (asked of goal_locator.onnx) or "
                         "false")
    look = q.get("look_m")
    if look is not None:
        look = check_look(look, "manifest goal_query.look_m")
        if not locator:
            raise ValueError("manifest goal_query.look_m needs locator true: only a goal locator is taught the view "
                             "from the look pose")
    return GoalQuerySpec(tuple(families), tuple(float(v) for v in off), ticks, locator, look)


class GoalQuery:
    """One command's goal query (module doc); inactive (`release` None) where the bundle has none, the family is
    not listed, the command names no two objects, or `enabled` is False."""

    def __init__(self, bundle, text: str, family: str | None, enabled: bool = True):
        spec = getattr(bundle, "goal_query", None)  # a torch stand-in (policy.oracle_eval) has none
        swapped = role_swap(text) if enabled and spec is not None and family in spec.families else None
        self.bundle, self.spec, self.swapped = bundle, spec, swapped
        self._query = None if swapped is None else bundle.embed(swapped)
        self._points: list[np.ndarray] = []
        self.point: np.ndarray | None = None

    @property
    def active(self) -> bool:
        return self._query is not None

    @property
    def settled(self) -> bool:
        """The point is held from now on (the first `ticks` inferences asked)."""
        return self._query is not None and len(self._points) >= self.spec.ticks

    @property
    def look(self) -> bool:
        """Asked from a look pose (runtime/look.py calls `ask` there), not on the policy's first inferences."""
        return self._query is not None and self.spec.look_m is not None

    def ask(self, images: dict, proprio: np.ndarray, stage: int = 0) -> None:
        """Ask the question once more about these frames (until `settled`); `point` is the median so far."""
        if self._query is None or self.settled:
            return
        grasp = self.bundle.goal_point(images, proprio, self._query, stage)
        self._points.append(grasp + np.asarray(self.spec.offset_m))
        self.point = np.median(np.stack(self._points), axis=0)

    def release(self, images: dict, proprio: np.ndarray, stage: int = 0) -> np.ndarray | None:
        """The (4,) release_point input for this inference (x, y, z base frame, flag 1), or None (the head's: no
        query, or a look that never got its answer)."""
        if self._query is None:
            return None
        if not self.look:
            self.ask(images, proprio, stage)
        return None if self.point is None else np.append(self.point, 1.0).astype(np.float32)
