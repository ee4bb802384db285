"""A pause the arm has already held: a chunk that opens by staying put, played from where it moves.

Why: the collector holds still for 0.5-0.6 s after each close and each let-go (datagen.primitives' GRASP_SECONDS
and RELEASE_SECONDS, datagen.articulated's), and the policy's two observation steps (0.2 s) do not say how much
of that pause has gone by. So at the handle, fingers closed, its chunks begin with a few actions that stay where
the arm is and push after them, and since a new chunk replaces the last at every tick, only those first actions
are ever played: drawer_put's closing phase held the handle for 20 s and timed out with the drawer open (seed
100556; policy/EXPERIMENTS.md, "A pause already held"). Once the arm has held still longer than any pause of the
collector's (`Pause.seconds` of the data's time, twice the longest), the chunk's leading actions that stay where
the arm is, with the gripper where it is, are dropped and the rest played from the next tick (the last action
held to keep the chunk's length). A chunk that stays put throughout, or moves from its first action, is played as
it is, and so is every chunk while the arm moves or the fingers are still closing or opening. The arm held still
against something it pushes (the chunk's first action away from the TCP) is not a pause and is left alone.

numpy only, like the bundle's inference path: the runtime's policy node and `sudd eval` both use it, on the
policy's own chunks (not a look's or a retreat's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.stage import GRIPPER_COLUMN as GRIPPER


@dataclass(frozen=True)
class Pause:
    seconds: float = 1.2  # data time held still before a chunk's leading pause counts as served (2 x 0.6 s)
    still_m: float = 0.01  # the TCP within this of where it stopped: still
    fingers: float = 0.08  # measured closure within this of where it stopped: the fingers are still too
    stay_m: float = 0.01  # a chunk's action within this of the TCP now, gripper request unchanged: staying put
    request: float = 0.25  # a gripper request that far from the one in effect is a close or a let-go


class ServedPause:
    """One command's stillness so far and the chunks it trims (module doc)."""

    def __init__(self, cfg: Pause = Pause(), enabled: bool = True):
        self.cfg, self.enabled = cfg, enabled
        self._anchor: np.ndarray | None = None  # (TCP position, closure, request) where the arm stopped
        self._since = 0.0
        self.trimmed = 0  # chunks whose leading pause was dropped
        self.dropped = 0  # actions dropped from them

    def still_for(self, proprio: np.ndarray, request: float, t: float) -> float:
        """Feed the newest proprio step (position, rot6d, closure) and the gripper request in effect at time `t`
        [s]; returns how long the arm has held still."""
        c = self.cfg
        now = np.array([*np.asarray(proprio, np.float64)[:3], float(proprio[GRIPPER]), float(request)])
        a = self._anchor
        if (a is None or np.linalg.norm(now[:3] - a[:3]) > c.still_m or abs(now[3] - a[3]) > c.fingers
                or abs(now[4] - a[4]) > c.request):
            self._anchor, self._since = now, t
        return t - self._since

    def chunk(self, actions: np.ndarray, proprio: np.ndarray, request: float, t: float,
              speed: float = 1.0) -> np.ndarray:
        """The policy's (n, Da) chunk, observed at `t` [s] and played at `speed` of the data's pace, with its
        leading pause dropped where the arm has already held one (module doc); else `actions` itself."""
        held = self.still_for(proprio, request, t)
        if not self.enabled or held * speed < self.cfg.seconds:
            return actions
        stays = ((np.linalg.norm(actions[:, :3] - np.asarray(proprio[:3]), axis=1) <= self.cfg.stay_m)
                 & (np.abs(actions[:, GRIPPER] - request) < self.cfg.request))
        lead = int(np.argmin(stays)) if not stays.all() else len(actions)
        if lead == 0 or lead == len(actions):
            return actions
        self.trimmed += 1
        self.dropped += lead
        return np.concatenate([actions[lead:], np.repeat(actions[-1:], lead, axis=0)])
