"""`sudd bench policy`: what a policy bundle costs at run time on this machine.

Figures: chunk latency (observation encoding + every DDIM step + unnormalization: one `Bundle.act`) p50/p99
at the bundle's default 2 intra-op threads and at 1, the split into obs encoding and one denoising step,
text-embedding latency, load time, parameter counts and the bytes of every file. Without a bundle, a
freshly initialized `small` policy is exported to a temporary directory (latency does not depend on the
weights) - so the figure exists before any training. Target: chunk p50 <= 25 ms for `small` on 2 cores.

Medians of one run; on a machine shared with other work the p99 mostly measures the neighbours.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from policy.bundle import Bundle


def _times(fn, n: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        t = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t
    return out * 1e3


def _pct(ms: np.ndarray) -> dict:
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "mean_ms": float(ms.mean()), "n": int(len(ms))}


def fresh_small_bundle(out_dir: str | Path, cache_dir: str | Path | None = None) -> Path:
    """Export an untrained `small` policy (identity normalization, no instructions) to out_dir."""
    import torch

    from policy.config import preset
    from policy.export import export_model
    from policy.model import DiffusionPolicy
    from policy.normalize import Normalizer

    torch.manual_seed(0)
    cfg = preset("small")
    export_model(DiffusionPolicy(cfg), Normalizer.identity(cfg.proprio_dim, cfg.action_dim), out_dir,
                 data_info={"tasks": [], "instructions": [], "note": "untrained: latency bench only"},
                 cache_dir=cache_dir)
    return Path(out_dir)


def run_policy_bench(quick: bool = False, bundle: str | Path | None = None, threads: tuple[int, ...] = (2, 1)) -> dict:
    n = 20 if quick else 200
    with tempfile.TemporaryDirectory(prefix="sudd-policy-bench-") as tmp:
        path = Path(bundle) if bundle else fresh_small_bundle(Path(tmp) / "bundle")
        t = time.perf_counter()
        b = Bundle.load(path, intra_op_num_threads=threads[0])
        load_ms = (time.perf_counter() - t) * 1e3
        m = b.manifest
        rng = np.random.default_rng(0)
        H, W = b.image_size
        imgs = {c: rng.integers(0, 256, (b.obs_horizon, H, W, 3), dtype=np.uint8) for c in b.cameras}
        proprio = rng.normal(size=(b.obs_horizon, b.proprio_dim)).astype(np.float32)
        emb = b.embed("pick up the red block and put it in the bowl")
        out = {"bundle": str(path) if bundle else f"fresh {m['config']['preset']} (untrained)",
               "preset": m["config"]["preset"], "sampler": m.get("diffusion", {}).get("sampler", "ddim"),
               "sampler_steps": b.sampler_steps,
               "load_ms": load_ms, "chunk": {}}
        for k in threads:
            bk = b if k == threads[0] else Bundle.load(path, intra_op_num_threads=k, verify_hashes=False)
            out["chunk"][f"threads_{k}"] = _pct(_times(lambda: bk.act(imgs, proprio, emb, rng=rng), n))
        # K chunks in one batch for backward coherence (policy/coherence.py), on the first thread count
        for kk in (4, 8):
            out["chunk"][f"samples_{kk}"] = _pct(_times(lambda: b.act(imgs, proprio, emb, rng=rng, samples=kk), n))
        # the bundle's own feed assembly (stage bins, the queries' points at flag 0), as act() and parity use it
        encode = lambda: b._encode(imgs, proprio, emb, 0, None)
        cond = encode()[0]
        x = rng.normal(size=(1, b.pred_horizon, b.action_dim)).astype(np.float32)
        step = {"noisy_actions": x, "timestep": np.array([50], np.int64), "cond": cond}
        out["obs_encoder"] = _pct(_times(encode, n))
        out["denoise_step"] = _pct(_times(lambda: b.sessions["denoiser"].run(None, step), n))
        if b.goal_query is not None:  # the first inferences of a command it lists also ask this (goal locator or head)
            out["goal_point"] = _pct(_times(lambda: b.goal_point(imgs, proprio, emb), n))
        sentences = ["pick up the red block and put it in the bowl", "open the top drawer, put the mug inside and close it"]
        k = iter(range(10**9))
        out["text_embed"] = _pct(_times(lambda: (b._cache.clear(), b.embed(sentences[next(k) % 2])), max(10, n // 4)))
        out["params"] = m.get("params", {})
        out["bytes"] = {f: v["bytes"] for f, v in m["files"].items()}
        out["bytes"]["total"] = sum(v["bytes"] for v in m["files"].values())
        out["target_p50_ms"] = 25.0
        out["meets_target"] = out["chunk"][f"threads_{threads[0]}"]["p50_ms"] <= 25.0
    return out


def format_table(figures: dict) -> str:
    lines = [f"policy bench: {figures['bundle']} ({figures['sampler_steps']} {figures['sampler']} steps), "
             f"load {figures['load_ms']:.0f} ms"]
    for name, f in figures["chunk"].items():
        lines.append(f"  chunk  {name:10s} p50 {f['p50_ms']:7.2f} ms   p99 {f['p99_ms']:7.2f} ms")
    for key in ("obs_encoder", "denoise_step", "goal_point", "text_embed"):
        if key not in figures:
            continue
        f = figures[key]
        lines.append(f"  {key:17s} p50 {f['p50_ms']:7.2f} ms   p99 {f['p99_ms']:7.2f} ms")
    lines.append("  params  " + ", ".join(f"{k} {v / 1e6:.2f} M" for k, v in figures["params"].items()))
    lines.append("  bytes   " + ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in figures["bytes"].items() if v > 1e5))
    lines.append(f"  target p50 <= {figures['target_p50_ms']} ms: {'met' if figures['meets_target'] else 'NOT met'}")
    return "\n".join(lines)
