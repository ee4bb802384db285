"""Per-cycle telemetry of the control loop in a fixed-size ring buffer, with a percentile summary.

Why a ring of preallocated arrays: the loop runs at 500 Hz and must not allocate per cycle or grow without
bound; the node that publishes telemetry (later) reads `summary()` at a low rate. Recorded per cycle:

* period: time since the previous cycle's start (s); jitter = period - nominal control period, i.e. how far
  the cycle started after its schedule (previous start + one period, as wait_period sleeps); a cycle is on
  time when its jitter <= late_tolerance x period
* compute: cycle start -> command sent (s)
* track_err: max |measured q - planned q at now| (rad): how well the arm follows the policy's timeline
"""

from __future__ import annotations

import numpy as np

FIELDS = ("t", "period", "jitter", "compute", "track_err", "desired", "sent")


class Telemetry:
    def __init__(self, size: int, nominal_period: float, late_tolerance: float = 0.25):
        self.size, self.nominal = int(size), float(nominal_period)
        self.late_limit = late_tolerance * nominal_period
        self._a = {k: np.full(self.size, np.nan) for k in FIELDS}
        self.n = 0  # cycles recorded in total

    def record(self, t: float, period: float, compute: float, track_err: float, desired: bool, sent: bool) -> None:
        i = self.n % self.size
        a = self._a
        a["t"][i] = t
        a["period"][i] = period
        a["jitter"][i] = period - self.nominal
        a["compute"][i] = compute
        a["track_err"][i] = track_err
        a["desired"][i] = desired
        a["sent"][i] = sent
        self.n += 1

    def arrays(self) -> dict[str, np.ndarray]:
        """The buffered cycles, oldest first."""
        n = min(self.n, self.size)
        start = self.n % self.size if self.n > self.size else 0
        idx = (start + np.arange(n)) % self.size
        return {k: v[idx] for k, v in self._a.items()}

    def summary(self) -> dict:
        """p50/p99/max of period, |jitter| and compute (ms), fraction on time, tracking error (mrad)."""
        a = self.arrays()
        out = {"cycles": int(self.n), "window": int(len(a["t"])), "nominal_ms": self.nominal * 1e3}
        per = a["period"][np.isfinite(a["period"])]
        if per.size:
            jit = np.abs(per - self.nominal)
            for name, x in (("period", per), ("jitter", jit), ("compute", a["compute"])):
                x = x[np.isfinite(x)]
                if x.size:
                    out[f"{name}_p50_ms"] = float(np.percentile(x, 50)) * 1e3
                    out[f"{name}_p99_ms"] = float(np.percentile(x, 99)) * 1e3
                    out[f"{name}_max_ms"] = float(x.max()) * 1e3
            out["on_time"] = float(np.mean(per - self.nominal <= self.late_limit))
            out["rate_hz"] = float(1.0 / per.mean())
        te = a["track_err"][np.isfinite(a["track_err"])]
        if te.size:
            out["track_err_p50_mrad"] = float(np.percentile(te, 50)) * 1e3
            out["track_err_max_mrad"] = float(te.max()) * 1e3
        return out


__all__ = ["Telemetry", "FIELDS"]
