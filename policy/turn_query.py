"""The turn query: how far the wrist must turn to grasp the command's object square to its faces, asked of a turn
locator on the way to the grasp, and held by the runtime on the policy's actions.

Why: the policy never turns the wrist for a block's yaw. Open loop on 40 unseen stack episodes, the chunk's turn
on the first frame follows the collector's with a slope of 0.04 (correlation 0.08); later frames follow it (0.8)
only because the recorded proprio is already turning. The frozen image encoders were never taught a square
block's yaw (the grasp-axis label is (0, 0) for a quarter-turn footprint, policy/grasp_axis.py), so nothing in
the features says which way to turn. In closed loop step 33 closes a uniform 0-45 degrees off the block's faces,
and stacks 95 % of the episodes it closes within 10 degrees against 62 % at 40-45. With the sim's true turn held
on its actions the same denoiser closes 0.1 degrees off (median) and places the block off the lower one 5 times in
120 against 12 (policy/EXPERIMENTS.md, "The wrist turn").

How: a turn locator (policy/goal_locator.py, the "turn" question: a copy of the encoders and head taught
`turn_label`, the turn relative to the wrist modulo the footprint's period, in the head's grasp-axis slot, on
views along the way to the grasp) is asked the command at every inference until the gripper first closes. An
answer is a (cos, sin) pair whose length says how sure it is (a regression onto unit vectors shrinks where the
frames do not tell: the object small, or out of view); one at least `min_norm` long sets the target yaw, the
wrist's yaw at that frame plus the turn, taken as the equal grasp nearest the yaw the command started at (so the
wrist never turns more than half a period, whatever the locator says). The runtime (runtime/wrist_turn.py) turns
each action of the chunk to that yaw, at a bounded rate, until the first grasp cycle ends; position, tilt and
gripper stay the policy's.

Torch-free: the runtime's policy node and `sudd eval` use it through the bundle; `sudd export --turn-locator RUN`
records it (the manifest's `turn_query`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.grasp_axis import turn_of, wrap, yaw_of

GRAPH = "turn_locator"
COLUMNS = slice(6, 8)  # the locator head's grasp-axis slot (policy.goal_locator.TURN_COLUMNS)
MIN_NORM = 0.5  # an answer shorter than this is not sure enough to turn on


@dataclass(frozen=True)
class TurnQuerySpec:
    """The manifest's `turn_query`: which families use it, the footprint period its answers are read for, and how
    long an answer must be to be acted on."""

    families: tuple[str, ...]
    period: float  # rad
    min_norm: float = MIN_NORM


def turn_query_spec(manifest: dict) -> TurnQuerySpec | None:
    """The validated `turn_query` of a manifest, None where it has none; a ValueError names the field."""
    q = manifest.get("turn_query")
    if q is None:
        return None
    if not isinstance(q, dict):
        raise ValueError(f"manifest turn_query: expected a table, got {type(q).__name__}")
    known = manifest.get("tasks") or []
    families = q.get("families")
    if not (isinstance(families, list) and families and all(f in known for f in families)):
        raise ValueError(f"manifest turn_query.families {families!r}: expected a non-empty list of the bundle's task "
                         f"families {known}")
    period = q.get("period_deg")
    if not (isinstance(period, (int, float)) and not isinstance(period, bool) and 0 < period <= 180):
        raise ValueError(f"manifest turn_query.period_deg {period!r}: expected the footprint's period in (0, 180] "
                         "degrees (a square block: 90)")
    least = q.get("min_norm", MIN_NORM)
    if not (isinstance(least, (int, float)) and not isinstance(least, bool) and 0.0 <= least <= 1.0):
        raise ValueError(f"manifest turn_query.min_norm {least!r}: expected the shortest answer acted on, in [0, 1]")
    return TurnQuerySpec(tuple(families), float(np.radians(period)), float(least))


class TurnQuery:
    """One command's turn query (module doc); inactive where the bundle has none, the family is not listed or
    `enabled` is False. `ask` on each inference before the first close; `target` is the yaw to hold [rad, base
    frame] from the first sure answer on (None before), `turn` that target from the command's start yaw."""

    def __init__(self, bundle, text: str, family: str | None, enabled: bool = True):
        spec = getattr(bundle, "turn_query", None)
        self.bundle, self.spec = bundle, spec
        active = enabled and spec is not None and family in spec.families
        self._text = bundle.embed(text) if active else None
        self.target: float | None = None
        self.start: float | None = None  # the wrist's yaw when first asked
        self.asked = self.sure = 0

    @property
    def active(self) -> bool:
        return self._text is not None

    @property
    def turn(self) -> float | None:
        """The target's turn from the start yaw [rad], within half the footprint's period either way (`ask` sets the
        target so); None before an answer."""
        if self.target is None:
            return None
        return float(self.target - self.start)

    def ask(self, images: dict, proprio: np.ndarray) -> None:
        """Ask about these frames; a sure answer sets `target` to the newest frame's wrist yaw plus its turn."""
        if not self.active:
            return
        wrist = float(yaw_of(np.asarray(proprio[-1, 3:9], np.float64)))
        if self.start is None:
            self.start = wrist
        label = np.asarray(self.bundle.turn_label(images, proprio, self._text), np.float64)
        self.asked += 1
        if float(np.linalg.norm(label)) >= self.spec.min_norm:
            self.sure += 1
            # Of the equal grasps the answer names, the one nearest the start yaw: asked again and again as the
            # wrist turns, a locator biased one way would otherwise walk the target round without end.
            P = self.spec.period
            self.target = self.start + wrap(wrist + turn_of(label, P) - self.start, P)
