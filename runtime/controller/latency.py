"""Online estimate of the execution latency: the lag between the commanded and the measured joint motion.

Why cross-correlation (UMI's method): the latency that matters is end to end (transport, the robot's servo
interpolation and lookahead filter, the joint servos), and it shows directly as the shift that best aligns the
sent joint targets with the measured joints. Velocities (differences) are correlated rather than positions,
so a static offset (gravity sag, calibration) does not bias the result; the peak is refined with a parabola
to sub-cycle resolution. With too little motion (the arm holding still) there is no estimate.
"""

from __future__ import annotations

import copy

import numpy as np


class LatencyEstimator:
    def __init__(self, period: float, window_s: float = 2.0, max_lag_s: float = 0.25):
        self.dt = float(period)
        self.n = max(16, int(round(window_s / period)))
        self.max_lag = max(2, int(round(max_lag_s / period)))
        self._cmd = np.full((self.n, 6), np.nan)
        self._meas = np.full((self.n, 6), np.nan)
        self._i = 0

    def record(self, commanded, measured) -> None:
        """One cycle: the joint target sent and the joints measured (NaN rows break nothing)."""
        k = self._i % self.n
        self._cmd[k] = commanded
        self._meas[k] = measured
        self._i += 1

    def copy(self) -> "LatencyEstimator":
        """A snapshot to estimate from outside the control thread's lock."""
        return copy.deepcopy(self)

    def mark_gap(self) -> None:
        """No command this cycle (stopped): keep the window's time axis regular."""
        self.record(np.nan, np.nan)

    def estimate(self, min_speed: float = 0.02, min_corr: float = 0.6) -> float | None:
        """Latency (s) maximising the correlation of commanded and measured joint velocities, or None."""
        if self._i < self.n:
            return None
        k = self._i % self.n
        cmd = np.roll(self._cmd, -k, axis=0)
        meas = np.roll(self._meas, -k, axis=0)
        vc, vm = np.diff(cmd, axis=0), np.diff(meas, axis=0)
        ok = np.isfinite(vc).all(axis=1) & np.isfinite(vm).all(axis=1)
        vc, vm = np.where(ok[:, None], vc, 0.0), np.where(ok[:, None], vm, 0.0)
        if np.sqrt(np.mean(vc ** 2)) / self.dt < min_speed / 6.0 ** 0.5:
            return None
        L = len(vc) - self.max_lag
        a = vc[:L]
        na = np.sqrt(np.sum(a * a))
        # every lag at once (one pass, no Python loop: this runs beside, or in, the 500 Hz control thread)
        b = np.lib.stride_tricks.sliding_window_view(vm, L, axis=0)  # (max_lag + 1, 6, L): vm[lag:lag + L]
        nb = np.sqrt(np.einsum("kjl,kjl->k", b, b))
        dots = np.einsum("lj,kjl->k", a, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.where((na > 0) & (nb > 0), dots / (na * nb), 0.0)
        j = int(np.argmax(corr))
        if corr[j] < min_corr:
            return None
        frac = 0.0
        if 0 < j < self.max_lag:
            c0, c1, c2 = corr[j - 1], corr[j], corr[j + 1]
            den = c0 - 2.0 * c1 + c2
            frac = 0.5 * (c0 - c2) / den if den < 0 else 0.0
        return (j + frac) * self.dt


__all__ = ["LatencyEstimator"]
