"""The handle keeps its height: while the fingers hold a drawer's handle, the arm stays at the height they closed on it.

Why: a drawer slides level on its rails, so a hand that holds its handle has nowhere to go but level; the denoiser's
chunks sink as they pull or push, up to 7 mm below where the fingers closed, and there the 2F-85's finger links press
down on the top edge of the drawer's front, 5 cm behind the handle. The force that builds is a protective stop: on
drawer_put seeds 100552, 100566 and 100577 (four chunks a tick) the arm closed the drawer from 0.9 open to 0.25-0.30
with the TCP sinking from 12.5-12.8 cm to 11.8-12.0 cm, and stopped at 156-164 N between a finger link and the front;
two seeds stopped the same way while pulling the drawer open (100502, 100553), the TCP 3-4 mm below where it closed
(policy/EXPERIMENTS.md, "The handle keeps its height"). The data collector's pull and push are level.

How: in a skill on a drawer's handle (HANDLE_FAMILIES: the command's family, or the running phase's), the TCP height
is noted at the first tick the fingers close on something: requested closed, measured more than SHORT short of the
request and less closed than EMPTY_CLOSED (beyond it nothing is between them). Until the request opens or the
fingers shut on nothing, every action of a chunk up to its first opening row has its height kept within BAND_M of
that. Positions across, turns and the gripper stay the policy's. Every action still goes through the safety layer.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import CLOSED, GRIPPER_COLUMN
from runtime.controller.gripper import EMPTY_CLOSED

# The families whose grasp is on a drawer's handle (a prismatic joint that runs level).
HANDLE_FAMILIES = ("drawer_open", "drawer_close")
BAND_M = 0.002  # how far from the height the fingers closed at an action may go, up or down
# Requested closed, the fingers this much short of the request and short of an empty close: they close on or hold
# something. Not the release guard's 0.15: the 2F-85 holds the 16 mm handle 0.86-0.88 closed where it takes it on
# the pads (the collector's drawer_close, seed 100004), and shuts to 0.96-0.99 on nothing.
SHORT = 0.05


class HandleHeight:
    """One command's handle height (module doc); inactive where `enabled` is False."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.height: float | None = None  # the TCP's z [m] where the fingers closed on the handle; None: not holding
        self.kept = 0  # chunks with an action moved back to the height

    def chunk(self, actions: np.ndarray, family: str | None, command: float, closure: float,
              tcp_z: float) -> np.ndarray:
        """The chunk (n, 10; base frame) with its heights kept while the handle is held, or as it was (module doc).
        `family` the running skill's family; `command` and `closure` the gripper's standing position request and
        measured closure (0 open .. 1 closed); `tcp_z` the TCP's height now [m]."""
        if command < CLOSED or closure >= EMPTY_CLOSED:
            self.height = None  # let go, never closed, or nothing between the fingers: the next hold notes its own
        elif self.height is None and command - closure > SHORT:
            self.height = float(tcp_z)
        if not (self.enabled and family in HANDLE_FAMILIES and self.height is not None):
            return actions
        opens = np.flatnonzero(actions[:, GRIPPER_COLUMN] < CLOSED)
        rows = slice(0, int(opens[0]) if len(opens) else len(actions))
        z = actions[rows, 2]
        kept = np.clip(z, self.height - BAND_M, self.height + BAND_M)
        if np.array_equal(kept, z):
            return actions
        out = actions.copy()
        out[rows, 2] = kept
        self.kept += 1
        return out
