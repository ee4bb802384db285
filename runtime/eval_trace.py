"""A tick-by-tick trace of a closed-loop episode, one CSV, to read how it failed.

A filmstrip (runtime.eval_filmstrip) shows what the scene looked like; a trace says what the arm did and what the
policy asked of it at every policy tick: the TCP, the fingers' command and closure, the drawer, the named object
and whether the fingers hold it, the first and last targets of the chunk made at that tick, and the controller's
and safety filter's events. A chunk that keeps asking the arm to stay put, a push aimed past a shut drawer, an
opening the safety filter held back: each reads off a few rows. `sudd eval --traces` writes one per failed policy
episode. Recording reads the sim state and changes nothing, so an episode with a trace runs exactly as one without.

Positions are in the robot's base frame, in centimetres; times in seconds of sim time.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from policy.stage import GRIPPER_COLUMN

COLUMNS = ("t", "tcp_x", "tcp_y", "tcp_z", "tcp_yaw_deg", "grip_cmd", "closure", "drawer",
           "target_x", "target_y", "target_z", "holds_target",
           "aim_x", "aim_y", "aim_z", "aim_grip", "end_x", "end_y", "end_z", "end_grip", "chunk", "events")


class Trace:
    """Call it with (world, instance) at every policy tick, as any observer of `run_policy_episode`;
    `chunk(actions, accepted)` with each chunk sent to the controller (its rows' xyz in metres, the gripper's
    request in policy.stage.GRIPPER_COLUMN) and `events(kinds)` with the controller's events since the last tick."""

    def __init__(self):
        self.rows: list[dict] = []
        self._view = None
        self._target: str | None = None

    def __call__(self, world, inst) -> None:
        from runtime.eval_progress import CABINET_PARAM, target_name
        from sim.state import StateView
        from sim.tasks.drawer import drawer_fraction

        if self._view is None:
            self._view = StateView(world)
            self._target = target_name(inst)
        T = world.tcp_pose()
        row = {"t": round(float(world.time), 3), **_cm("tcp", T[:3, 3]),
               "tcp_yaw_deg": round(math.degrees(math.atan2(T[1, 0], T[0, 0])), 1),
               "grip_cmd": round(float(world.gripper_command()), 3),
               "closure": round(float(world.gripper_position()), 3)}
        if CABINET_PARAM in inst.params:
            row["drawer"] = round(float(drawer_fraction(self._view)), 3)
        if self._target is not None:
            row.update(_cm("target", self._view.position(self._target)))
            row["holds_target"] = int(bool(self._view.holding(self._target)))
        self.rows.append(row)

    def chunk(self, actions: np.ndarray, accepted: bool) -> None:
        if not self.rows:
            return
        a, g = np.asarray(actions, float), GRIPPER_COLUMN
        self.rows[-1].update({**_cm("aim", a[0, :3]), "aim_grip": round(float(a[0, g]), 2),
                              **_cm("end", a[-1, :3]), "end_grip": round(float(a[-1, g]), 2),
                              "chunk": "accepted" if accepted else "rejected"})

    def events(self, kinds: list[str]) -> None:
        if self.rows and kinds:
            before = self.rows[-1].get("events", "")
            self.rows[-1]["events"] = ";".join(filter(None, [before, *kinds]))

    def save(self, path: Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS, restval="")
            w.writeheader()
            w.writerows(self.rows)
        return path


def _cm(prefix: str, xyz) -> dict:
    return {f"{prefix}_{k}": round(100.0 * float(v), 1) for k, v in zip("xyz", xyz)}
