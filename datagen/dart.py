"""Noise injection into the demonstrations (DART, Laskey et al. 2017): the arm is pushed off the planned path
while the recorded actions stay the plan's, so the policy sees states a little off the demonstrations and
learns the way back to them.

Why: a distilled policy drifts a few centimetres from the demonstrations; a collector that executes its plans
exactly never shows what to do from there. Here the executed TCP path is the plan plus a smooth random
offset (position only; the gripper's orientation is kept); the recorder labels every step with the planned
target, so the action at a perturbed state points back to the plan.

The offset is on while the arm moves and off while the gripper acts (grasps, releases: the object must still
be picked and placed for the episode to count); it fades over `fade_s` into each gripper action, so an
approach or a descent comes in from off the plan and ends exactly on it, the correction the policy needs
near contact. It starts and ends each motion at zero, so the next motion starts where the plan said.

A grasp offset (`grasp_sigma`) is the exception, on purpose: with the path noise alone every close in the data
happens exactly on the plan, so a policy learns to close only there, and one that arrives a centimetre off
hovers open beside the object (traced in closed loop). With it each grasp happens at a constant horizontal
offset (never vertical: the fingers must not be pushed into the table), faded in over the approach's last
`fade_s` and out over the lift's first, while the labels still point at the plan: close when near, and
steer the rest of the way while closing.
"""

from __future__ import annotations

import numpy as np

from datagen.trajectory import Motion

# Segments where the arm moves: the offset may be on. Everything else (grasp, release, articulation) keeps it
# off, and the envelope's ramps reach zero before them.
MOVING = frozenset({"move to pre-grasp", "approach", "lift", "move to pre-place", "descend", "retreat", "go home"})
KNOT_S = 0.1  # the offset is an Ornstein-Uhlenbeck process sampled at these knots, then interpolated
SMOOTH_S = 0.2  # and box-filtered over this window: no step-to-step jitter for the servo to chase


def step_labels(motion: Motion, dt: float) -> list[str]:
    """The running segment's label at every physics step `datagen.trajectory.execute` takes."""
    return [seg.label for seg in motion.segments for _ in range(seg.steps(dt))]


def _erode(e: np.ndarray, slope: float) -> np.ndarray:
    """In place: each value at most its neighbour's plus `slope`, so every fall to a low value is a ramp."""
    for k in range(1, len(e)):
        e[k] = min(e[k], e[k - 1] + slope)
    for k in range(len(e) - 2, -1, -1):
        e[k] = min(e[k], e[k + 1] + slope)
    return e


def envelope(labels: list[str], dt: float, fade_s: float) -> np.ndarray:
    """Per step in [0, 1]: 1 inside moving segments, 0 elsewhere and at both ends of the motion, with ramps of
    `fade_s` that stay below the target (an erosion: the offset is gone when the gripper acts)."""
    e = np.array([1.0 if lab in MOVING else 0.0 for lab in labels])
    if len(e) == 0:
        return e
    e[0] = e[-1] = 0.0
    return _erode(e, dt / max(fade_s, dt))


def grasp_envelope(labels: list[str], dt: float, fade_s: float) -> np.ndarray:
    """Per step in [0, 1]: 1 while the gripper grasps, with ramps of `fade_s` out into the steps around it (a
    dilation: the offset is whole before the fingers close) and 0 at both ends of the motion."""
    g = np.array([0.0 if lab == "grasp" else 1.0 for lab in labels])
    if len(g) == 0:
        return g
    slope = dt / max(fade_s, dt)
    g = 1.0 - _erode(g, slope)  # the dilation of the grasp steps
    g[0] = g[-1] = 0.0
    return _erode(g, slope)


def smooth_offsets(n: int, dt: float, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) TCP offsets in metres: a stationary OU process of std `sigma` and correlation time `tau_s`."""
    if n == 0:
        return np.zeros((0, 3))
    knots = int(np.ceil(n * dt / KNOT_S)) + 2
    a = np.exp(-KNOT_S / tau_s)
    x = np.empty((knots, 3))
    x[0] = rng.normal(0.0, sigma, 3)
    for k in range(1, knots):
        x[k] = a * x[k - 1] + np.sqrt(1.0 - a * a) * rng.normal(0.0, sigma, 3)
    t = np.arange(n) * dt
    out = np.column_stack([np.interp(t, np.arange(knots) * KNOT_S, x[:, j]) for j in range(3)])
    width = max(1, int(round(SMOOTH_S / dt)))
    pad = np.pad(out, ((width // 2, width - 1 - width // 2), (0, 0)), mode="edge")
    kernel = np.ones(width) / width
    return np.column_stack([np.convolve(pad[:, j], kernel, mode="valid") for j in range(3)])


def joint_offsets(motion: Motion, kin, dt: float, rng: np.random.Generator, sigma: float,
                  tau_s: float = 1.0, fade_s: float = 0.5, damping: float = 1e-3,
                  grasp_sigma: float = 0.0) -> np.ndarray:
    """(steps, 6) joint offsets to add to `motion`'s targets, step by step as `execute` runs them: the TCP
    moves by the enveloped offset (damped least squares on the Jacobian at the planned joints; the rotation
    is held). grasp_sigma > 0 adds one horizontal offset of that std per axis around a pick's "grasp" segment."""
    labels = step_labels(motion, dt)
    d = smooth_offsets(len(labels), dt, sigma, tau_s, rng) * envelope(labels, dt, fade_s)[:, None]
    if grasp_sigma > 0:  # drawn after the path's offsets, which therefore stay those of grasp_sigma = 0
        held = np.array([*rng.normal(0.0, grasp_sigma, 2), 0.0])
        d = d + grasp_envelope(labels, dt, fade_s)[:, None] * held
    planned = np.concatenate([seg.targets(dt) for seg in motion.segments]) if motion.segments else np.zeros((0, 6))
    out = np.zeros((len(labels), 6))
    for k in np.flatnonzero(np.any(d != 0.0, axis=1)):
        J = kin.jacobian(planned[k])
        twist = np.concatenate([d[k], np.zeros(3)])
        out[k] = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(6), twist)
    return out


__all__ = ["MOVING", "envelope", "grasp_envelope", "joint_offsets", "smooth_offsets", "step_labels"]
