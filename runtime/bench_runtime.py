"""Runtime benchmark: bus hop, controller loop timing, and camera-frame-to-first-action latency end to end.

    sudd bench runtime [--json] [--quick]

* `bus`: one Zenoh hop of a 320x240 RGB frame (runtime.bench_bus, shared memory when available), measured
  before the stack starts, so nothing else competes for the CPU.
* `controller`: period and |jitter| of ControllerLoop at 500 Hz on the realtime SimRig (its telemetry), from
  the robot node of the full stack below (so it runs next to physics, cameras, IK and the policy process),
  and how far the arm is from its plan (`track_err`, joints): late cycles step the periods they missed
  (ControllerConfig.catch_up_periods), so a loaded host costs timing, not tracking.
* `latency`: the whole sim stack (`sudd run --sim` processes, real Zenoh sessions) with the given bundle:
  per chunk, capture time of its observation -> the policy node publishes it (`obs_to_publish`) -> the
  robot node receives it (`obs_to_receive`) -> ControllerLoop.submit accepted it (`obs_to_accepted`, IK
  included). p50/p99 in ms. Target: obs_to_receive p50 <= 50 ms on this CPU.

Default bundle: the shipped default (policy/bundles/multitask) once set-up has restored its text encoder; otherwise
an untrained `small` policy exported to a temp dir by `make_test_bundle` (in a subprocess: the runtime never
imports torch), with its action range set around the sim arm's home pose so the chunks are executable
(small motions near home), and the episode's instruction recorded as trained. The JSON names which ran.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from runtime.run_cli import DEFAULT_BUNDLE

LATENCY_TARGET_P50_MS = 50.0

_EXPORT = r"""
import json, sys
import numpy as np, torch
from policy.config import preset
from policy.export import export_model
from policy.model import DiffusionPolicy
from policy.normalize import Normalizer
out, instructions, tasks, cache = sys.argv[1], json.loads(sys.argv[2]), json.loads(sys.argv[3]), sys.argv[4] or None
torch.manual_seed(0)
cfg = preset("small")
home = np.array([-0.1333, 0.4919, 0.3321]); r6 = np.array([1.0, 0, 0, 0, -1.0, 0])
def rng_map(lo, hi):
    scale = (2.0 / (hi - lo)).astype(np.float32)
    return scale, (-1.0 - lo * scale).astype(np.float32), lo.astype(np.float32), hi.astype(np.float32)
a_lo = np.concatenate([home - 0.03, r6 - 1e-3, [0.0]]); a_hi = np.concatenate([home + 0.03, r6 + 1e-3, [1.0]])
p_lo = np.concatenate([home - 0.5, -np.ones(6), [0.0], -np.pi * np.ones(6)])
p_hi = np.concatenate([home + 0.5, np.ones(6), [1.0], np.pi * np.ones(6)])
norm = Normalizer(*rng_map(p_lo, p_hi), *rng_map(a_lo, a_hi))
export_model(DiffusionPolicy(cfg), norm, out, data_info={"tasks": tasks, "instructions": instructions,
             "note": "untrained small policy, actions within 3 cm of the home pose: runtime tests/bench only"},
             cache_dir=cache)
"""


def test_cache_dir() -> Path:
    """The text-encoder export cache the policy tests use too (content-keyed, never stale)."""
    return Path(tempfile.gettempdir()) / f"sudd-test-cache-{os.getuid()}"


def make_test_bundle(out_dir: str | Path, instructions: list[str], tasks: list[str] = ("pick_place",),
                     timeout_s: float = 600.0) -> Path:
    """Export an UNTRAINED `small` bundle (~30 s) whose actions stay within 3 cm of the sim home pose and
    whose manifest lists `instructions` as trained (so the policy node accepts them)."""
    out = Path(out_dir)
    subprocess.run([sys.executable, "-c", _EXPORT, str(out), json.dumps(list(instructions)), json.dumps(list(tasks)),
                    str(test_cache_dir())], check=True, timeout=timeout_s,
                   env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")})
    return out


def episode_instruction(task: str = "pick_place", seed: int = 0, dr: str = "off") -> str:
    from sim.build import build_episode

    return build_episode(task, seed, dr, "fast").instruction


def run_stack(bundle: str | Path, duration_s: float = 10.0, task: str = "pick_place", seed: int = 0,
              command: str = "", hub: str = "tcp/127.0.0.1:0", **robot_overrides):
    """Run the sim stack for `duration_s` after ready; returns the Launcher (reports, exit codes)."""
    from runtime.launch import Launcher, sim_stack

    la = Launcher(sim_stack(str(bundle), task=task, seed=seed, **robot_overrides), hub=hub)
    with la:
        info = la.wait_ready()
        la.say(command or info["robot"].get("instruction") or "do the task", "bench")
        la.monitor(duration_s=duration_s)
    return la


def run_runtime_bench(quick: bool = False, bundle: str | Path | None = None) -> dict:
    from runtime.bench_bus import run_bus_bench

    t_start = time.perf_counter()
    result: dict = {"quick": quick, "target_obs_to_receive_p50_ms": LATENCY_TARGET_P50_MS}
    bus = run_bus_bench(quick=quick, frame_only=True)  # 5 x 300 hops: one short run is too noisy
    key = "frame_shm" if bus.get("shm_available") else "frame_copy"
    result["bus_frame_320x240_hop_ms"] = {"p50": bus["hop"][key]["p50_ms"], "p99": bus["hop"][key].get("p99_ms"),
                                          "path": key}
    with tempfile.TemporaryDirectory(prefix="sudd-runtime-bench-") as tmp:
        if bundle is None and (DEFAULT_BUNDLE / "text_encoder.onnx").exists():
            bundle = DEFAULT_BUNDLE  # the latency target is for the policy that ships
        if bundle is None:  # a checkout whose set-up has not restored the shipped text encoder
            bundle = make_test_bundle(Path(tmp) / "bundle", [episode_instruction()])
            result["bundle"] = "fresh small (untrained, actions near home)"
        else:
            result["bundle"] = str(bundle)
        la = run_stack(bundle, duration_s=5.0 if quick else 20.0)
    rob, pol = la.reports.get("robot", {}), la.reports.get("policy", {})
    cs = rob.get("controller_summary", {})
    result["controller_500hz"] = {k: cs.get(k) for k in ("cycles", "rate_hz", "period_p50_ms", "period_p99_ms",
                                                          "jitter_p50_ms", "jitter_p99_ms", "compute_p50_ms",
                                                          "compute_p99_ms", "on_time", "track_err_p50_mrad",
                                                          "track_err_max_mrad")}
    lat = rob.get("latency_ms", {})
    result["latency_ms"] = {"obs_to_publish": lat.get("publish"), "obs_to_receive": lat.get("receive"),
                            "obs_to_accepted": lat.get("accepted"), "inference": pol.get("inference_ms")}
    result["chunks"] = {"published": pol.get("chunks"), "received": rob.get("chunks_received"),
                        "accepted": rob.get("chunks_accepted"), "rejected": rob.get("chunks_rejected")}
    p50 = (lat.get("receive") or {}).get("p50")
    result["target_met"] = p50 is not None and p50 <= LATENCY_TARGET_P50_MS
    result["load_1min"] = os.getloadavg()[0]
    result["wall_s"] = round(time.perf_counter() - t_start, 1)
    return result


def format_table(r: dict) -> str:
    def fmt(d):
        if not d:
            return "-"
        return "  ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in d.items())

    lines = [f"runtime bench ({'quick' if r.get('quick') else 'full'}, bundle: {r.get('bundle')}, "
             f"load {r.get('load_1min', 0):.1f})",
             f"  bus hop, 320x240 frame (ms)        {fmt(r.get('bus_frame_320x240_hop_ms'))}",
             f"  controller 500 Hz                  {fmt(r.get('controller_500hz'))}"]
    for k, v in (r.get("latency_ms") or {}).items():
        lines.append(f"  latency {k:27s}(ms) {fmt(v)}")
    lines.append(f"  chunks                             {fmt(r.get('chunks'))}")
    lines.append(f"  target obs->receive p50 <= {r.get('target_obs_to_receive_p50_ms')} ms: "
                 f"{'met' if r.get('target_met') else 'NOT met'}")
    return "\n".join(lines)


if __name__ == "__main__":
    out = run_runtime_bench(quick="--quick" in sys.argv)
    print(json.dumps(out, indent=2) if "--json" in sys.argv else format_table(out))
