"""Noise schedules and the sampler updates, in plain numpy (also applied to torch tensors: same arithmetic).

numpy-only on purpose: training (torch), export (baked into the manifest), the checks and the runtime-side
loop in `policy.bundle` (which must not import torch) all take the schedule and the update from here, so the
bundle runs exactly the numbers the policy was trained and verified with.

- DDPM betas: `squaredcos_cap_v2` (Nichol & Dhariwal 2021: alpha_bar(t) = cos^2((t/T + 0.008)/1.008 * pi/2),
  betas capped at 0.999), the Diffusion Policy default; `linear` (1e-4..0.02) for comparison.
- DDIM timesteps use "trailing" spacing (Lin et al. 2024, "Common Diffusion Noise Schedules and Sample Steps
  are Flawed"): with 8 of 100 steps the first evaluation is at t=99, where the input really is pure noise.
  The "leading" spacing of the original DDIM starts at t=84 (alpha_bar = 0.06), a mismatch with the
  N(0, I) initial sample that shows as a bias at few steps. The last step jumps to alpha_bar = 1 (x0).
- Deterministic DDIM (eta = 0) with x0 clipped to [-1, 1], where every normalized action dimension lives.
- Flow matching (objective "flow"; Lipman et al. 2023, Liu et al. 2023 "rectified flow"): the straight path
  x_s = (1 - s) a + s eps from the action (s = 0) to noise (s = 1); the network predicts its velocity
  u = eps - a and sampling integrates it with Euler steps from s = 1 to 0. Its timestep k (the network's
  input, as DDPM's) is noise level s = (k + 1) / T, so the trailing timesteps serve both. A straight path is
  followed exactly by any number of Euler steps, one included, where the predicted velocity is exact.
"""

from __future__ import annotations

import math

import numpy as np


def betas(num_train_timesteps: int = 100, schedule: str = "squaredcos_cap_v2") -> np.ndarray:
    T = num_train_timesteps
    if schedule == "squaredcos_cap_v2":
        def alpha_bar(t):
            return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

        return np.array([min(1 - alpha_bar((i + 1) / T) / alpha_bar(i / T), 0.999) for i in range(T)], np.float64)
    if schedule == "linear":
        return np.linspace(1e-4, 0.02, T, dtype=np.float64)
    raise ValueError(f"unknown beta schedule {schedule!r}")


def alphas_cumprod(num_train_timesteps: int = 100, schedule: str = "squaredcos_cap_v2") -> np.ndarray:
    """(T,) float64: alpha_bar_t, the signal fraction of x_t = sqrt(ab) x0 + sqrt(1 - ab) eps."""
    return np.cumprod(1.0 - betas(num_train_timesteps, schedule))


def ddim_schedule(num_train_timesteps: int = 100, inference_steps: int = 8,
                  schedule: str = "squaredcos_cap_v2") -> dict:
    """The whole inference loop as data: timesteps (descending), alpha_bar at each and at its successor."""
    T, n = num_train_timesteps, inference_steps
    if not 1 <= n <= T:
        raise ValueError(f"inference steps {n} must be in [1, {T}]")
    ts = np.round(np.arange(T, 0, -T / n)).astype(np.int64) - 1
    ab = alphas_cumprod(T, schedule)
    prev = np.concatenate([ab[ts[1:]], [1.0]])
    return {"timesteps": ts.tolist(), "alpha_bar": ab[ts].tolist(), "alpha_bar_prev": prev.tolist()}


def flow_schedule(num_train_timesteps: int = 100, inference_steps: int = 8) -> dict:
    """Euler steps of a flow-matching sampler as data: timesteps (descending), noise level s at each and at
    its successor (the last goes to s = 0, the action)."""
    T, n = num_train_timesteps, inference_steps
    if not 1 <= n <= T:
        raise ValueError(f"inference steps {n} must be in [1, {T}]")
    ts = np.round(np.arange(T, 0, -T / n)).astype(np.int64) - 1
    s = (ts + 1) / T
    return {"timesteps": ts.tolist(), "sigma": s.tolist(), "sigma_next": np.concatenate([s[1:], [0.0]]).tolist()}


def flow_noise_level(timesteps, num_train_timesteps: int):
    """Noise level s in (0, 1] of integer timesteps (numpy arrays or torch tensors)."""
    return (timesteps + 1) / num_train_timesteps


def flow_step(x, u, sigma: float, sigma_next: float, clip: bool = True):
    """One Euler step x_s -> x_s' of the velocity u = eps - a (numpy arrays or torch tensors). With `clip`,
    the action estimate a = x - s u is clipped to [-1, 1] first (as DDIM clips x0), then the step lands on
    the path through it: x_s' = (1 - s') a + s' eps with eps = x + (1 - s) u."""
    if not clip:
        return x + (sigma_next - sigma) * u
    a = (x - sigma * u).clip(-1.0, 1.0)
    return (1.0 - sigma_next) * a + sigma_next * (x + (1.0 - sigma) * u)


def schedule_steps(schedule: dict) -> list[tuple[int, float, float]]:
    """(timestep, coefficient, next coefficient) per step of a DDIM or flow schedule (as the manifest holds it)."""
    keys = ("sigma", "sigma_next") if "sigma" in schedule else ("alpha_bar", "alpha_bar_prev")
    return list(zip(schedule["timesteps"], schedule[keys[0]], schedule[keys[1]]))


def step_function(schedule: dict):
    """The update that goes with a schedule: `flow_step` for a flow schedule, else `ddim_step`."""
    return flow_step if "sigma" in schedule else ddim_step


def ddim_step(x, eps, alpha_bar: float, alpha_bar_prev: float, clip: bool = True):
    """One deterministic DDIM update x_t -> x_prev from the predicted noise (numpy arrays or torch tensors)."""
    x0 = (x - math.sqrt(1.0 - alpha_bar) * eps) / math.sqrt(alpha_bar)
    if clip:
        x0 = x0.clip(-1.0, 1.0)
    return math.sqrt(alpha_bar_prev) * x0 + math.sqrt(1.0 - alpha_bar_prev) * eps
