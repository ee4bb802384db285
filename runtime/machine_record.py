"""Where a run ran: the machine and the packages an evaluation's episodes and a training's weights depend on.

Why: `sudd eval` with a fixed latency replays the same seeds to the tick, but only on the same physics and
inference. A fresh install of newer mujoco or onnxruntime moved drawer_put's episodes; a new machine with the same
packages moved 77 of step 33's 120 stack episodes (policy/EXPERIMENTS.md, "The same bundle on another machine"):
numpy's, MuJoCo's and onnxruntime's kernels follow the CPU's vector instructions, and a closed loop through
contact carries the last bit of a sum into another episode. The rates carry over; the episodes do not. So every
eval records where it ran, and one resumed elsewhere says so. Training too (policy/train.py, with torch's version):
the s48 recipe trained again on the same data hash gave a denoiser with another release gain and other episodes
(policy/EXPERIMENTS.md, "s48 again on this machine"), so a run records its machine and the bundle carries it.
"""

from __future__ import annotations

import json
import platform
import re
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


EVAL_PACKAGES = ("numpy", "mujoco", "onnxruntime")  # what computes an episode
TRAIN_PACKAGES = ("numpy", "torch")  # what computes a training step


def library_versions(packages: tuple[str, ...] = EVAL_PACKAGES) -> dict[str, str]:
    """The CPU (`cpu_description`), Python and the packages' versions, by name: version."""
    out = {"python": platform.python_version(), "cpu": cpu_description()}
    for name in packages:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "missing"
    return out


def environment_change(out: Path, resuming: bool, packages: tuple[str, ...] = EVAL_PACKAGES) -> str:
    """What differs between the machine and packages OUT's results were started on (OUT/environment.json, written
    by the first run into OUT) and these, e.g. "cpu: AMD EPYC (avx2) -> Intel Xeon (avx512f)"; "" when nothing
    does or nothing is resumed."""
    path, now = out / "environment.json", library_versions(packages)
    try:
        before = json.loads(path.read_text()) if resuming else None
    except (OSError, ValueError):
        before = None  # results from before the file was written, or a file cut short: nothing to compare
    if not isinstance(before, dict):
        path.write_text(json.dumps(now, indent=2))
        return ""
    return "; ".join(f"{k}: {before.get(k)} -> {v}" for k, v in now.items() if before.get(k) != v)


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU's model, the widest vector instruction set it offers and its family and model numbers where told,
    e.g. "AMD EPYC (avx2; family 25 model 1)": the kernels numpy, torch, MuJoCo and onnxruntime pick, and so the
    last bits of their sums, follow it."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    model = re.search(r"^model name\s*:\s*(.+)$", cpuinfo, re.M)
    flags = re.search(r"^(?:flags|Features)\s*:\s*(.+)$", cpuinfo, re.M)
    name = model.group(1).strip() if model else (platform.processor() or platform.machine() or "unknown")
    have = set(flags.group(1).split()) if flags else set()
    widest = next((f for f in ("avx512f", "avx2", "avx", "sse4_2", "asimd") if f in have), None)
    # A cloud VM may name only "AMD EPYC": the family and model tell a Zen 2 host from a Zen 3 one
    family = re.search(r"^cpu family\s*:\s*(\d+)$", cpuinfo, re.M)
    number = re.search(r"^model\s*:\s*(\d+)$", cpuinfo, re.M)
    generation = f"family {family.group(1)} model {number.group(1)}" if family and number else ""
    detail = "; ".join(x for x in (widest, generation) if x)
    return f"{name} ({detail})" if detail else name
