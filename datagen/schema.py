"""One recorded episode, as the episode runner produces it and the dataset store writes it.

Per step (at `CONTROL_HZ`): both cameras' colour images, proprioception, the action (absolute end-effector
target: position, 6-D rotation, gripper), and which subtask was running. Per episode: the language (root
task and subtask labels), retries, the success label with the check snippet's verdict beside the ground-truth
predicate, the seed and the domain-randomization record. Schema changes bump `SCHEMA_VERSION`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SCHEMA_VERSION = 1
CONTROL_HZ = 10.0  # observation/action rate of the recorded data (the policy's rate)
CAMERAS = ("scene", "wrist")  # dataset names of sim.scene.SCENE_CAMERA and sim.robot.WRIST_CAMERA
IMAGE_SIZE = (128, 128)  # (height, width) of recorded images
# A step of an injected failure (`sudd datagen --perturb/--perturb-grasp`: the gripper closing on air, the object
# let go in transit) has subtask PERTURBED: the recovery that follows is a demonstration, the failure is not,
# so training never takes its actions as targets. PERTURBATION is the motion segments' label for those steps.
PERTURBED = -2
PERTURBATION = "perturbation"
# proprio = TCP position (3), TCP rotation as the first two columns of its matrix (6), gripper closure (1),
# joint angles (6)
PROPRIO_DIM = 16
# action = target TCP position (3), target rotation 6-D (6), gripper command (1: 0 open .. 1 closed)
ACTION_DIM = 10


def rot6d(R: np.ndarray) -> np.ndarray:
    """The 6-D rotation representation (Zhou et al. 2019): the first two columns of R, column-major."""
    return np.concatenate([R[:, 0], R[:, 1]])


def rot6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """Gram-Schmidt back to a rotation matrix (robust to a network's non-orthogonal output)."""
    a, b = np.asarray(d6[:3], float), np.asarray(d6[3:6], float)
    x = a / np.linalg.norm(a)
    b = b - x * (x @ b)
    y = b / np.linalg.norm(b)
    return np.column_stack([x, y, np.cross(x, y)])


@dataclass
class EpisodeData:
    """Everything recorded for one episode; arrays share the leading step axis (length T)."""

    images: dict[str, np.ndarray]  # camera -> (T, H, W, 3) uint8
    proprio: np.ndarray  # (T, PROPRIO_DIM) float32
    action: np.ndarray  # (T, ACTION_DIM) float32
    subtask: np.ndarray  # (T,) int16 index into meta["subtasks"]; -1 before the first, PERTURBED (-2) in an
    #                      injected failure
    time: np.ndarray  # (T,) float64 sim seconds
    meta: dict = field(default_factory=dict)  # JSON-able: see `EPISODE_META_KEYS`

    def __len__(self) -> int:
        return int(self.action.shape[0])

    def validate(self) -> None:
        T = len(self)
        for name, arr in self.images.items():
            if name not in CAMERAS or arr.dtype != np.uint8 or arr.ndim != 4 or arr.shape[0] != T:
                raise ValueError(f"image stream {name!r}: expected (T={T}, H, W, 3) uint8, got {arr.shape} {arr.dtype}")
        for name, arr, dim in (("proprio", self.proprio, PROPRIO_DIM), ("action", self.action, ACTION_DIM)):
            if arr.shape != (T, dim) or not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: expected finite ({T}, {dim}), got {arr.shape}")
        if self.subtask.shape != (T,) or self.time.shape != (T,):
            raise ValueError("subtask and time must have one entry per step")
        missing = [k for k in EPISODE_META_KEYS if k not in self.meta]
        if missing:
            raise ValueError(f"episode meta is missing {missing}")


EPISODE_META_KEYS = (
    "task",  # task family name
    "seed",  # episode seed: (task, seed) reproduces the episode
    "instruction",  # the root task's language
    "subtasks",  # list of subtask labels (language), indexed by `subtask`
    "success",  # ground-truth task predicate at the end (sim/tasks)
    "check_success",  # the plan's check snippets' verdict for the whole task
    "label",  # the success label used for training, and which source it came from
    "retries",  # total retries across subtasks
    "planner",  # "offline" or "llm:<model>"
    "dr",  # the domain-randomization record
)


def episode_success(meta: dict) -> bool:
    """The training label of an episode: meta["label"]["value"] (what the data generator chose), else the
    synthetic episodes' meta["label"]["success"], else meta["success"]."""
    label = meta.get("label")
    if isinstance(label, dict):
        for key in ("value", "success"):
            if label.get(key) is not None:
                return bool(label[key])
    return bool(meta.get("success"))


def perturbed_actions(subtask: np.ndarray) -> np.ndarray:
    """(T,) subtask -> (T,) bool: which recorded actions command an injected failure. The action of step t is
    the target the arm had at step t + 1 (the last step's is its own), so it is one step ahead of the label."""
    p = np.asarray(subtask) == PERTURBED
    return np.concatenate([p[1:], p[-1:]])


LEVEL_SHARE = 0.01  # a gripper command held in at least this share of the steps is a level the data uses


def gripper_levels(commands) -> tuple[float, ...]:
    """Recorded gripper commands (0 open .. 1 closed; an array or a list of per-episode arrays) -> the
    finger positions the collector used, to 0.01, always with open (0) and closed (1): what the runtime's
    gripper channel snaps the policy's regressed value to (runtime/controller/gripper.py). The ramps between
    levels are a few steps each and drop out under LEVEL_SHARE."""
    c = np.concatenate([np.ravel(a) for a in commands]) if isinstance(commands, (list, tuple)) else np.ravel(commands)
    values, counts = np.unique(np.round(np.clip(c, 0.0, 1.0), 2), return_counts=True)
    used = values[counts >= LEVEL_SHARE * max(len(c), 1)]
    return tuple(float(v) for v in sorted(set(used.tolist()) | {0.0, 1.0}))


def grasp_and_release_per_step(action: np.ndarray, subtask: np.ndarray | None = None) -> np.ndarray:
    """(T, Da) recorded actions (gripper command 0 open .. 1 closed) -> (T, 2) int: for each step, the step of
    the grasp it is on its way to (or in) and of the release that grasp leads to. A grasp is where a closed
    run of the gripper command starts, its release where the run ends (the last step if it never does).

    With the episode's `subtask` (T,), injected failures (datagen.schema.PERTURBED) do not count: a close on
    air is no grasp, and a run that a drop in transit ends was a grasp but no release, so every step before
    the drop points at the grasp it made and at the release that finally put the object in place. Where no
    grasp or release is left, the last one stands (the last step if there was none)."""
    shut = np.asarray(action)[:, -1] > 0.5
    T = len(shut)
    bad = perturbed_actions(subtask) if subtask is not None else np.zeros(T, bool)
    grasps, releases = [], []  # (step, the step until which it is the next one)
    t = 0
    while t < T:
        if not shut[t]:
            t += 1
            continue
        end = t
        while end < T and shut[end]:
            end += 1
        opened = min(end, T - 1)
        if not bad[t]:
            grasps.append((t, opened))
            if not bad[opened] or end == T:
                releases.append((opened, opened))
        t = end
    out = np.full((T, 2), T - 1, np.int64)
    for column, steps in enumerate((grasps, releases)):
        if steps:
            starts, ends = (np.array(v) for v in zip(*steps))
            out[:, column] = starts[np.minimum(np.searchsorted(ends, np.arange(T), side="right"), len(ends) - 1)]
    return out


def grasp_and_release_steps(action: np.ndarray, subtask: np.ndarray | None = None) -> tuple[int, int]:
    """The first step's `grasp_and_release_per_step`: the episode's first grasp and the release it leads to
    (the step where the gripper first closes and next opens, in an episode without injected failures)."""
    g, r = grasp_and_release_per_step(action, subtask)[0]
    return int(g), int(r)
