"""Warm start: a fresh run's first weights taken from another run's checkpoint (its EMA weights).

Why: on a 2-core CPU a run is hours. A variant that only adds inputs (aux_condition's 6 conditioning inputs)
can start from a trained run instead of from nothing. Tensors of equal shape are copied. A Linear whose
input grew at the end (the denoiser's FiLM conditioning, when the global cond gains inputs) gets the old
columns and zeros for the new ones, so at step 0 the new model computes exactly what the source did and
training alone decides how much the new inputs matter. Any other difference is refused, naming the tensor.

From a `sudd pretrain` run (its dataset.json says "pretrain") only the PRETRAINED modules are taken,
whatever the rest's shapes: the rest of such a run never trained, so a policy with another observation
horizon can start from it.

`load_pretrained_into` (`sudd train --init-from RUN --encoders-from PRETRAIN_RUN`) then replaces the encoders and
head by a later pretraining's: the denoiser goes on from RUN, on what the new encoders see.

The source may also be an exported bundle (a directory with manifest.json, such as policy/bundles/demo): its
weights are rebuilt from its ONNX graphs (policy.bundle_import, checked against the bundle before use) and
taken whole, as from a run's checkpoint.

The new run also takes the source's normalization stats, so the copied weights see the inputs they were
trained on; the source, its checkpoint and what grew are recorded in RUN/warm_start.json (and the bundle's
manifest, under training).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

from policy.normalize import Normalizer

RECORD = "warm_start.json"
# what `sudd pretrain` trains: from a pretrain run only these are taken (its denoiser and projections are untrained)
PRETRAINED = ("obs_encoder.images", "aux_head")


def source_checkpoint(source_run: str | Path) -> Path:
    from policy.train import latest_checkpoint

    path = latest_checkpoint(source_run)
    if path is None:
        raise FileNotFoundError(f"warm start: {source_run} has no checkpoint (checkpoints/step_*.pt); "
                                f"give a trained run directory")
    return path


def source_normalizer(source_run: str | Path) -> Normalizer:
    return Normalizer.load(Path(source_run) / "stats.npz")


def is_pretrain_run(run_dir: str | Path) -> bool:
    """Whether a run directory was written by `sudd pretrain` (its dataset.json says "pretrain")."""
    info = Path(run_dir) / "dataset.json"
    return info.is_file() and "pretrain" in json.loads(info.read_text())


def load_into(model: torch.nn.Module, source_run: str | Path) -> dict:
    """Copy the source run's EMA weights into `model` (see the module docstring); returns the record."""
    from policy.bundle_import import is_bundle

    if is_bundle(source_run):
        old, record = _from_bundle(source_run)
        return {**record, **_copy_into(model, old, Path(source_run) / "manifest.json"), "learned": learned(source_run)}
    path = source_checkpoint(source_run)
    state = torch.load(path, map_location="cpu", weights_only=False)
    old = state["ema"]["model"]
    pretrain = is_pretrain_run(source_run)
    if pretrain:
        old = {k: v for k, v in old.items() if k.startswith(tuple(p + "." for p in PRETRAINED))}
    return {"source": str(source_run), "checkpoint": str(path), "step": int(state["step"]),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), **_copy_into(model, old, path),
            **({} if pretrain else {"learned": learned(source_run)})}


def learned(source: str | Path) -> dict:
    """{"tasks", "instructions"} a policy's weights were trained on: a bundle's manifest lists them; a run's are
    its data's and its own warm start's. Why: a fine-tune on a few families' episodes still knows the others,
    and its bundle must list them, or the policy node refuses their commands (runtime.nodes.policy_node)."""
    from policy.bundle_import import is_bundle

    source = Path(source)
    if is_bundle(source):
        m = json.loads((source / "manifest.json").read_text())
        return {"tasks": sorted(m.get("tasks", [])), "instructions": sorted(m.get("instructions", []))}
    info = json.loads((source / "dataset.json").read_text()) if (source / "dataset.json").is_file() else {}
    before = (read_record(source) or {}).get("learned", {})
    return {k: sorted(set(info.get(k, [])) | set(before.get(k, []))) for k in ("tasks", "instructions")}


def load_pretrained_into(model: torch.nn.Module, pretrain_run: str | Path, normalizer: Normalizer) -> dict:
    """Replace `model`'s image encoders and aux head (PRETRAINED) by a `sudd pretrain` run's (after `load_into`
    took the rest from another run): a denoiser trained on one pretraining goes on with a later one's encoders.
    Refused unless the pretrain run's proprio normalization is the run's own (its head reads it)."""
    if not is_pretrain_run(pretrain_run):
        raise ValueError(f"--encoders-from {pretrain_run}: not a `sudd pretrain` run (its dataset.json does not say "
                         "\"pretrain\"); give the directory `sudd pretrain --out` wrote")
    theirs = source_normalizer(pretrain_run)
    for key in ("proprio_scale", "proprio_offset"):
        if not torch.allclose(torch.as_tensor(getattr(theirs, key)), torch.as_tensor(getattr(normalizer, key))):
            raise ValueError(f"--encoders-from {pretrain_run}: its {key} differs from the run's (--init-from's): "
                             "pretrain it --init-from the same chain of runs, so both read proprio alike")
    path = source_checkpoint(pretrain_run)
    state = torch.load(path, map_location="cpu", weights_only=False)
    prefixes = tuple(p + "." for p in PRETRAINED)
    old = {k: v for k, v in state["ema"]["model"].items() if k.startswith(prefixes)}
    own = {k: v for k, v in model.state_dict().items() if k.startswith(prefixes)}
    if set(old) != set(own):
        raise ValueError(f"--encoders-from {pretrain_run}: its encoders and head have other tensors "
                         f"({sorted(set(old) ^ set(own))[:3]}); pretrain with this run's config")
    return {"source": str(pretrain_run), "checkpoint": str(path), "step": int(state["step"]),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), **_copy_into(model, old, path)}


def load_locator_into(model: torch.nn.Module, bundle_dir: str | Path, graph: str) -> dict:
    """Copy a bundle's locator (goal_locator or object_locator, rebuilt from its graph by
    policy.bundle_import.locator_from_bundle) into `model`'s encoders and head; returns the record. Why: to teach a
    shipped locator more views, or to read another crop, from where it left off rather than from the policy's
    encoders, when its run is gone."""
    from policy.bundle_import import locator_from_bundle

    source, record = locator_from_bundle(bundle_dir, graph)
    old = {k: v for k, v in source.state_dict().items() if k.startswith(tuple(p + "." for p in PRETRAINED))}
    path = Path(bundle_dir) / f"{graph}.onnx"
    return {"source": str(bundle_dir), "bundle": True, "locator": graph,
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "rebuilt_max_abs_err": record["rebuilt_max_abs_err"], **_copy_into(model, old, path)}


def _from_bundle(bundle_dir: str | Path) -> tuple[dict, dict]:
    from policy.bundle_import import model_from_bundle

    source, _, manifest = model_from_bundle(bundle_dir)
    path = Path(bundle_dir) / "manifest.json"
    return source.state_dict(), {
        "source": str(bundle_dir), "bundle": True, "step": int(manifest.get("training", {}).get("step", 0)),
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "parity": manifest["imported"]["parity"]}


def _copy_into(model: torch.nn.Module, old: dict, path: Path) -> dict:
    """Copy `old` into `model` (equal shapes; a Linear's inputs may grow); what grew and what is new."""
    new = model.state_dict()
    extra = sorted(set(old) - set(new))
    if extra:
        raise ValueError(f"warm start from {path}: the new model has no {extra[:3]} (a different architecture)")
    grown, fresh = [], sorted(set(new) - set(old))
    for name, target in new.items():
        if name not in old:
            continue
        src = old[name]
        if src.shape == target.shape:
            target.copy_(src)
        elif src.dim() == 2 and src.shape[0] == target.shape[0] and src.shape[1] < target.shape[1]:
            target.zero_()
            target[:, :src.shape[1]] = src
            grown.append(f"{name} {tuple(src.shape)} -> {tuple(target.shape)}")
        else:
            raise ValueError(f"warm start from {path}: {name} is {tuple(src.shape)} there and "
                             f"{tuple(target.shape)} here; only a Linear's inputs may grow (at the end)")
    model.load_state_dict(new)
    return {"grown": grown, "new": fresh}


def write_record(run_dir: Path, record: dict) -> None:
    (run_dir / RECORD).write_text(json.dumps(record, indent=2))


def read_record(run_dir: str | Path) -> dict | None:
    path = Path(run_dir) / RECORD
    return json.loads(path.read_text()) if path.is_file() else None
