"""Samples an executing episode at the policy rate: both cameras, proprioception, commanded targets.

It is the `observer` of `datagen.trajectory.execute`: called after every physics step, it records a sample
whenever the policy clock ticks. The action of step t is the commanded end-effector target of step t + 1,
so a policy trained on it learns to output where the arm should be one control period later.
"""

from __future__ import annotations

import numpy as np

from datagen.schema import (ACTION_DIM, CAMERAS, CONTROL_HZ, IMAGE_SIZE, PERTURBATION, PERTURBED, PROPRIO_DIM,
                            EpisodeData, rot6d)
from sim.kinematics import Kinematics
from sim.randomize import corrupt_image, episode_sensor_params
from sim.render import CameraRenderer
from sim.robot import TCP_OFFSET_Z, WRIST_CAMERA
from sim.scene import SCENE_CAMERA

CAMERA_NAMES = {"scene": SCENE_CAMERA, "wrist": WRIST_CAMERA}


class Recorder:
    """Collects one episode's samples; `finish(meta)` turns them into an `EpisodeData`."""

    def __init__(self, episode, image_size=IMAGE_SIZE, hz: float = CONTROL_HZ, shadows: bool | None = None):
        self.world = episode.world
        self.kin = Kinematics.with_tcp_z(self.world.variant, TCP_OFFSET_Z)
        self.period = 1.0 / hz
        self.next_t = 0.0
        self.subtask = -1
        self._rng = episode.rngs.sensor
        self._sensor = episode_sensor_params(episode)
        h, w = image_size
        self._cams = CameraRenderer(self.world, w, h, shadows=shadows)
        self._images: dict[str, list[np.ndarray]] = {c: [] for c in CAMERAS}
        self._proprio: list[np.ndarray] = []
        self._target: list[np.ndarray] = []
        self._subtasks: list[int] = []
        self._times: list[float] = []

    def __call__(self, world, label: str = "", planned: np.ndarray | None = None) -> None:
        """`planned`: the joints the plan commands now when the executed ones are perturbed (datagen.dart);
        the action is then the plan's target, not the perturbed command. A step whose segment is an injected
        failure (`label` PERTURBATION) is recorded with subtask PERTURBED."""
        if world.time + 1e-9 < self.next_t:
            return
        self.next_t += self.period
        self.sample(planned, perturbed=label == PERTURBATION)

    def sample(self, planned: np.ndarray | None = None, perturbed: bool = False) -> None:
        w = self.world
        for name in CAMERAS:
            img = self._cams.rgb(CAMERA_NAMES[name])
            self._images[name].append(corrupt_image(img, self._sensor, self._rng))
        T = w.tcp_pose()
        q = w.arm_q() + self._rng.normal(0.0, self._sensor.q_noise_std, 6) if self._sensor.q_noise_std else w.arm_q()
        self._proprio.append(np.concatenate([T[:3, 3], rot6d(T[:3, :3]), [w.gripper_position()], q]))
        Tc = self.kin.fk(w.arm_target() if planned is None else planned)
        self._target.append(np.concatenate([Tc[:3, 3], rot6d(Tc[:3, :3]), [w.gripper_goal()]]))
        self._subtasks.append(PERTURBED if perturbed else self.subtask)
        self._times.append(w.time)

    @property
    def steps(self) -> int:
        """Samples recorded so far."""
        return len(self._proprio)

    def start(self) -> None:
        """The first sample, at the episode's start, before any step."""
        self.next_t = self.world.time + self.period
        self.sample()

    def window(self, n: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The newest n samples (images per camera, proprio), oldest first; the first sample repeats before
        the start, as the training windows pad (a closed-loop evaluation observes through this)."""
        idx = np.clip(np.arange(len(self._proprio) - n, len(self._proprio)), 0, None)
        images = {c: np.stack([v[i] for i in idx]) for c, v in self._images.items()}
        return images, np.stack([self._proprio[i] for i in idx]).astype(np.float32)

    def finish(self, meta: dict) -> EpisodeData:
        """Samples so far as an episode; the last step's action is its own (resting) target."""
        self.close()
        targets = np.asarray(self._target, dtype=np.float32)
        action = np.concatenate([targets[1:], targets[-1:]], axis=0)
        data = EpisodeData(
            images={c: np.stack(v) for c, v in self._images.items()},
            proprio=np.asarray(self._proprio, dtype=np.float32).reshape(-1, PROPRIO_DIM),
            action=action.reshape(-1, ACTION_DIM),
            subtask=np.asarray(self._subtasks, dtype=np.int16),
            time=np.asarray(self._times, dtype=np.float64),
            meta=dict(meta, sensor=self._sensor.record()),
        )
        data.validate()
        return data

    def observations(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The samples' camera images {camera: (T, H, W, 3)} and proprioception (T, PROPRIO_DIM) so far, for
        callers that record views rather than episodes (datagen.views)."""
        images = {c: np.stack(v) for c, v in self._images.items()}
        return images, np.asarray(self._proprio, dtype=np.float32).reshape(-1, PROPRIO_DIM)

    def close(self) -> None:
        if self._cams is not None:
            self._cams.close()
            self._cams = None
