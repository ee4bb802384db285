"""A torch policy rebuilt from an exported bundle's ONNX graphs, so a shipped bundle can be trained on.

    model, normalizer, manifest = model_from_bundle("policy/bundles/demo")

Why: a bundle is what a user has. The torch checkpoints of the run that made it are not in the repo (out/ runs
are the day's), and remaking the shipped policy from nothing is hours on a small CPU (its RECIPE.md), so
fine-tuning it on new data, or on more task families, starts here (`sudd train --init-from BUNDLE`).

How: export leaves most weights under their parameter names, but constant folding rewrites the rest (a
GroupNorm's scale reshaped to (C, 1, 1), a Linear's weight transposed for MatMul, the FiLM linears stacked
into one matrix), under generated names. Rather than know each rewrite, a probe model of the bundle's config
is exported by the same code with every parameter element set to its own index, k * 2**-21 (exact in
float32): each folded element then names the parameter element it was copied from. A second probe with the
values negated tells copies from constants that depend on no parameter (timestep frequencies, the proprio
normalization taken from stats.npz). Each bundle initializer is then read back into the parameter elements
its probe twin names. The rebuilt model must reproduce the bundle within the export's own parity tolerances
(policy.parity), or nothing is returned.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import torch

from policy.config import config_from_dict
from policy.fp16 import SUFFIX as FP16_SUFFIX
from policy.model import DiffusionPolicy
from policy.normalize import Normalizer

SCALE = 2.0 ** -21  # k * SCALE is exact in float32 for k < 2**24: up to 16 M parameters


def is_bundle(path: str | Path) -> bool:
    return (Path(path) / "manifest.json").is_file()


def _graph(path: Path) -> tuple[dict[str, np.ndarray], list[tuple[str, list[str]]]]:
    """A graph's initializers as float32 arrays under their original names (fp16 storage undone, merged
    ones under each of their names), and its nodes as (op type, input names) without the Casts and
    Identities that storage and merging added."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    inits = {}
    for t in graph.initializer:
        name = t.name[:-len(FP16_SUFFIX)] if t.name.endswith(FP16_SUFFIX) else t.name
        a = numpy_helper.to_array(t)
        inits[name] = a.astype(np.float32) if a.dtype == np.float16 else a
    nodes = []
    for n in graph.node:
        if n.op_type == "Cast" and n.input[0].endswith(FP16_SUFFIX):
            continue
        if n.op_type == "Identity" and n.input[0] in inits:  # the exporter's alias for a merged initializer
            inits[n.output[0]] = inits[n.input[0]]
            continue
        nodes.append((n.op_type, list(n.input)))
    return inits, nodes


def _slots(nodes: list[tuple[str, list[str]]], names) -> dict[str, tuple[int, int]]:
    """Where each of `names` is first read: (node index, input index)."""
    out: dict[str, tuple[int, int]] = {}
    for i, (_, inputs) in enumerate(nodes):
        for j, name in enumerate(inputs):
            if name in names and name not in out:
                out[name] = (i, j)
    return out


def _probe_graphs(cfg, normalizer: Normalizer, sign: float, opset: int, out_dir: Path) -> dict[str, tuple]:
    """Export a probe model whose parameter element k holds sign * (k + 1) * SCALE; its graphs (`_graph`)."""
    from policy.export import graph_specs, write_policy_graphs

    write_policy_graphs(_probe_model(cfg, normalizer, sign), out_dir, opset, fp16=False)
    return {key: _graph(out_dir / spec["file"]) for key, spec in graph_specs(cfg).items() if key != "text_encoder"}


def _probe_model(cfg, normalizer: Normalizer, sign: float) -> DiffusionPolicy:
    probe = DiffusionPolicy(cfg).eval()
    probe.set_proprio_stats(normalizer)
    k = 1
    with torch.no_grad():
        for p in probe.parameters():
            n = p.numel()
            p.copy_((sign * SCALE * torch.arange(k, k + n, dtype=torch.float64)).float().reshape(p.shape))
            k += n
    if k >= 2 ** 24:
        raise ValueError(f"bundle import: {k} parameters, more than the probe's exact range (16 M)")
    return probe


def _read_back(model: DiffusionPolicy, bundle_dir: Path, pos: dict, neg: dict,
               keys: tuple[str, ...] = ("obs_encoder", "denoiser")) -> dict:
    """Fill `model`'s parameters from the bundle's graphs `keys` (KEY.onnx), guided by the probes; coverage."""
    flat = torch.cat([p.detach().reshape(-1).double() for p in model.parameters()])
    covered = torch.zeros(flat.numel(), dtype=torch.bool)
    for key in keys:
        path = bundle_dir / f"{key}.onnx"
        (mine, my_nodes), (their_inits, their_nodes) = pos[key], _graph(path)
        if [op for op, _ in my_nodes] != [op for op, _ in their_nodes]:
            raise ValueError(f"bundle import: {path}'s nodes differ from this code's export of its config: it was "
                             f"exported by another version (manifest producer); re-export it from its run")
        # by where a weight is read, not by its generated name: names are the tracer's counters
        for name, (i, j) in _slots(my_nodes, mine).items():
            a = mine[name]
            if a.dtype != np.float32:
                continue
            b = their_inits.get(their_nodes[i][1][j])
            if b is None or b.shape != a.shape:
                raise ValueError(f"bundle import: {path} reads no {a.shape} weight where this code's export reads "
                                 f"{name}; re-export the bundle from its run with this version")
            copy = (neg[key][0][name] == -a) & (a != 0)
            idx = np.rint(a[copy].astype(np.float64) / SCALE).astype(np.int64) - 1
            flat[torch.from_numpy(idx)] = torch.from_numpy(b[copy].astype(np.float64))
            covered[torch.from_numpy(idx)] = True
    absent, k = [], 0
    with torch.no_grad():
        for name, p in model.named_parameters():
            n = p.numel()
            part = covered[k:k + n]
            if not part.any():
                absent.append(name)  # used by training only (not in any graph): keeps its fresh value
            elif not part.all():
                raise ValueError(f"bundle import: {name} is only partly in the graphs ({int(part.sum())} of {n} "
                                 f"elements): its folded form is not a copy this reader can invert")
            else:
                p.copy_(flat[k:k + n].reshape(p.shape).float())
            k += n
    return {"parameters": int(flat.numel()), "not_in_graphs": absent}


def model_from_bundle(bundle_dir: str | Path) -> tuple[DiffusionPolicy, Normalizer, dict]:
    """The torch policy of a bundle (its weights as stored: EMA, fp16-rounded), its normalizer and manifest;
    manifest["imported"] holds the coverage and the parity figures of the rebuilt model against the bundle."""
    from policy.bundle import Bundle
    from policy.parity import check_parity

    bundle_dir = Path(bundle_dir)
    Bundle.load(bundle_dir, warmup=False)  # refuses a broken bundle with its reason before anything else
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    cfg = config_from_dict(manifest["config"])
    normalizer = Normalizer.load(bundle_dir / "stats.npz")
    with tempfile.TemporaryDirectory() as tmp:
        pos = _probe_graphs(cfg, normalizer, 1.0, manifest["opset"], Path(tmp))
        neg = _probe_graphs(cfg, normalizer, -1.0, manifest["opset"], Path(tmp))
    model = DiffusionPolicy(cfg)
    model.set_proprio_stats(normalizer)
    coverage = _read_back(model, bundle_dir, pos, neg)
    model.eval()
    parity = check_parity(model, normalizer, bundle_dir)  # raises ExportError when the rebuild is off
    manifest["imported"] = {**coverage, "parity": parity}
    return model, normalizer, manifest


def locator_from_bundle(bundle_dir: str | Path, graph: str) -> tuple[DiffusionPolicy, dict]:
    """The torch locator behind a bundle's `graph` (goal_, object_ or turn_locator, policy/goal_locator.py) and
    the record of the run it came from (the manifest's query table's `locator_from`), rebuilt as
    `model_from_bundle` rebuilds the policy: its encoders and head read back from the graph, the rest of the
    model (the denoiser, which a locator never runs) left fresh; refused unless the rebuild reproduces the graph
    within the export's parity tolerance."""
    from policy.bundle import Bundle
    from policy.export_graphs import _write_locator
    from policy.goal_locator import graph_spec
    from policy.parity import STEP_TOL, _locator_parity

    bundle_dir = Path(bundle_dir)
    b = Bundle.load(bundle_dir, warmup=False)
    manifest = json.loads((bundle_dir / "manifest.json").read_text())
    table = manifest.get({"goal_locator": "goal_query", "object_locator": "object_query",
                          "turn_locator": "turn_query"}.get(graph, ""))
    if graph not in manifest.get("graphs", {}) or not table:
        raise ValueError(f"bundle import: {bundle_dir} has no {graph} graph (its graphs: "
                         f"{', '.join(manifest.get('graphs', {}))})")
    # a locator's own crop (policy.goal_locator.check_compatible); bundles from before it was recorded: the policy's
    crop = table.get("locator_from", {}).get("crop_size", manifest["config"]["crop_size"])
    cfg = config_from_dict({**manifest["config"], "crop_size": list(crop)})
    normalizer = Normalizer.load(bundle_dir / "stats.npz")
    spec = graph_spec(cfg, graph)
    probes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for sign in (1.0, -1.0):
            _write_locator(_probe_model(cfg, normalizer, sign), Path(tmp), spec, manifest["opset"], False)
            probes[sign] = {graph: _graph(Path(tmp) / spec["file"])}
    model = DiffusionPolicy(cfg)
    model.set_proprio_stats(normalizer)
    _read_back(model, bundle_dir, probes[1.0], probes[-1.0], keys=(graph,))
    model.eval()
    with torch.no_grad():
        err = _locator_parity(model, normalizer, b, 3, 0, graph)
    if not err <= STEP_TOL:
        raise ValueError(f"bundle import: the rebuilt {graph} is {err:.2e} off {bundle_dir}'s graph (tolerance "
                         f"{STEP_TOL:.0e}); export the bundle again from its runs")
    return model, {**table.get("locator_from", {}), "bundle": str(bundle_dir), "rebuilt_max_abs_err": err}
