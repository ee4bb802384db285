"""Export a trained run to a self-contained policy bundle directory, verified before it is published.

    export("runs/pp", "bundles/pp")      # EMA weights of the latest checkpoint, fp16 weight storage

Bundle layout (format "sudd-policy-bundle", version 1):

    manifest.json        format/version, opset, graph I/O (names, shapes, dtypes), horizons, dims, cameras and
                         image/crop size, tasks + known instructions, the pace per task family (policy.pace),
                         data content hash, config, DDIM schedule, parameter counts, file sizes + sha256, weight
                         storage, text-encoder and parity figures
    obs_encoder.onnx     image_<camera> uint8 (B,To,H,W,3) full frames, proprio (B,To,Dp) normalized (Dp: the
                         recorded proprio, then dims.stage_bins one-hot grasp-cycle classes, policy.stage),
                         text_embedding (B,I) -> cond (B,G); the centre crop and /255 are inside the graph;
                         I = 384, or 768 with "instruction": {"goal_clause": true} (policy.instruction);
                         with "release_input": true also release_point (B,4) in and aux_points (B,dims.aux) out,
                         with "grasp_input": true also grasp_point (B,4) in (policy/object_query.py)
                         (the goal query, policy/goal_query.py; its table is the manifest's "goal_query")
    goal_locator.onnx    with a goal locator (policy/goal_locator.py): image_<camera>, text_embedding -> aux_points
    object_locator.onnx  with an object query (policy/object_query.py): the same I/O, the object question's locator
    denoiser.onnx        noisy_actions (B,Tp,Da), timestep (B,) int64, cond (B,G) -> noise_pred (B,Tp,Da)
    text_encoder.onnx    input_ids, attention_mask (B,L) int64 -> embedding (B,384), weight-only int8 MiniLM
    tokenizer/           tokenizer.json (+ vocab and configs) for `tokenizers`
    text_reference.npy   the text encoder's embeddings of fixed sentences (checks a rebuilt text encoder)
    stats.npz            normalization (policy.normalize.STAT_KEYS)

One denoising step per graph, the DDIM loop in the loader (numpy), rather than the loop unrolled into one
graph with the noise as an input: measured on this 2-core CPU the two cost the same (16.7 vs 16.8 ms for
8 steps; onnxruntime's per-call overhead is ~20 us against ~2 ms of per-op work per step), and the step
graph is 8x smaller to load, can be checked step by step, and lets a deployment trade steps for speed.

The policy graphs store their weights as float16 by default (policy.fp16: half the bytes, same fp32 speed),
so a bundle can be committed; the torch weights are rounded to fp16 first, the parity check stays exact,
and what the rounding changes is recorded ("weights"). The text encoder and tokenizer come from the
installed MiniLM package and are marked restorable (policy.text_export): a committed bundle leaves them
out and `sudd export --restore-text-encoder` rebuilds them. Before anything is published, the bundle is
loaded with `policy.bundle.Bundle` and compared with torch on random inputs (policy.parity: each graph,
every denoising step and the final action chunk, manifest "parity"). The graphs are traced in
policy/export_graphs.py.
"""

from __future__ import annotations

import copy
import datetime
import json
import shutil
import tempfile
from pathlib import Path

import torch

from policy.bundle import sha256_file
from policy.config import TEXT_DIM
from policy.export_graphs import (OPSET, _onnx_export, _rounded, _write_locator, graph_specs,  # noqa: F401
                                  write_policy_graphs)
from policy.goal_locator import GRAPH as LOCATOR_GRAPH
from policy.goal_locator import OBJECT_GRAPH, TURN_GRAPH, load_locator, object_query_table
from policy.goal_locator import graph_spec as locator_spec
from policy.model import DiffusionPolicy, count_params, film_dim
from policy.normalize import STAT_KEYS, Normalizer
from policy.pace import check_pace_table
from policy.phased import check_phased
from policy.object_query import check_keep_release, check_release_shift, with_skill_families
from policy.turn_query_measure import turn_query_table
from policy.parity import check_parity, rounding_cost
from policy.sampling import schedule_for
from policy.warm_start import read_record

FORMAT, FORMAT_VERSION = "sudd-policy-bundle", 1


# The manifest key holding the sampler's schedule, and what the denoiser graph predicts, per objective.
SAMPLER_KEY = {"ddpm": "ddim", "flow": "euler"}
PREDICTS = {"ddpm": "epsilon", "flow": "velocity"}


def export(run_dir: str | Path, out_bundle_dir: str | Path, checkpoint: str | Path | None = None, ema: bool = True,
           opset: int = OPSET, cache_dir: str | Path | None = None, fp16_weights: bool = True,
           inference_steps: int | None = None, noise_scale: float | None = None,
           text_encoder_from: str | Path | None = None, pace: dict[str, float] | None = None,
           goal_query: dict | None = None, goal_locator: str | Path | None = None,
           object_query: dict | None = None, phased: list[str] | None = None,
           queries_from: str | Path | None = None, turn_locator: str | Path | None = None,
           object_release_shift: tuple[float, float, float] | None = None,
           object_keep_release: list[str] | None = None) -> dict:
    """Export a training run (latest checkpoint, EMA weights), or a bundle again (its weights rebuilt from its
    graphs, policy.bundle_import; its data, training and pace records kept), to a bundle directory; returns the
    manifest.

    inference_steps: DDIM steps the bundle samples with, instead of the run's config (the network is trained
    for every timestep, so this is an inference choice: more steps, smoother chunks, more latency).
    noise_scale: the sampling temperature, instead of the run's config (also an inference choice).
    text_encoder_from: copy the text encoder from this bundle instead of building it from the installed package.
    pace: {task family or "*": speed} the runtime plays the chunks at (policy.pace; default every family at 1,
    or a bundle's own table).
    phased: the families `sudd run` and `sudd eval` run as their phases by default (policy.phased; default none,
    or a bundle's own list).
    goal_query: {"families": [...], "data": DIR, "ticks": n}: measure the goal query on DIR's episodes
    (policy.goal_query_measure) and export the obs encoder with the release point input (config release_input).
    goal_locator: with goal_query, a `sudd pretrain --goal-locator` run (policy/goal_locator.py) the query asks
    instead of the policy's head, exported as goal_locator.onnx and measured so.
    object_query: {"families": [...], "data": DIR, "locator": RUN, "ticks": n}: the object query
    (policy/object_query.py) of that `sudd pretrain --object-locator` run, exported as object_locator.onnx, its
    error measured on DIR's episodes, and the obs encoder with the grasp point input (config grasp_input).
    queries_from: a bundle whose goal and object queries (their tables as measured, their locators rebuilt from
    its graphs, policy.bundle_import.locator_from_bundle) this export keeps: a denoiser fine-tuned on frozen
    encoders changes neither, and their runs and data need not still exist. With goal_query or object_query, the
    other one is kept and that one measured anew (e.g. a new goal locator beside the bundle's object locator).
    turn_locator: a `sudd pretrain --turn-locator` run (policy/turn_query.py), exported as turn_locator.onnx; its
    table records the run's own check (on the run's --data). A bundle's turn query is kept by `queries_from` like
    the others.
    object_release_shift: (dx, dy, dz) metres added to the object query's release point
    (policy.object_query, `release_shift_m`); default a kept query's own, a measured one's none.
    object_keep_release: the families whose grasp cycles after the object query's still get its drop point
    (policy.object_query, `keep_release`); default a kept query's own, a measured one's none."""
    from policy.bundle_import import is_bundle
    from policy.config import load_policy_config

    run_dir = Path(run_dir)
    if is_bundle(run_dir):
        if checkpoint is not None or not ema:
            raise ValueError(f"{run_dir} is a bundle: it holds one set of weights (the export's), so --checkpoint and "
                             "--no-ema do not apply; give the run directory to choose its checkpoint")
        source = json.loads((run_dir / "manifest.json").read_text())
        asked = source.get("goal_query")
        if asked and goal_query is None and queries_from is None:  # its table is measured, not rebuilt
            raise ValueError(f"{run_dir} asks a goal query for {', '.join(asked.get('families', []))}"
                             f"{' of its goal locator' if asked.get('locator') else ''}; exported again without "
                             "--goal-query it would not: give --goal-query FAMILY --goal-query-data DATA"
                             f"{' --goal-locator RUN' if asked.get('locator') else ''} again")
        if source.get("object_query") and object_query is None and queries_from is None:
            raise ValueError(f"{run_dir} asks an object query of its object locator; exported again without "
                             "--object-query it would not: give --object-query FAMILY --object-query-data DATA "
                             "--object-locator RUN again")
        model, normalizer, data_info, training, kept = _bundle_source(run_dir)
        pace = kept["pace"] if pace is None else pace
        phased = kept["phased"] if phased is None else phased
    else:
        from policy.train import load_run_model

        model, _, training = load_run_model(run_dir, checkpoint, ema)
        warm = read_record(run_dir)
        normalizer = Normalizer.load(run_dir / "stats.npz")
        data_info = json.loads((run_dir / "dataset.json").read_text())
        if (run_dir / "environment.json").exists():  # where it trained: elsewhere the recipe gives other weights
            training["machine"] = json.loads((run_dir / "environment.json").read_text())
        if warm is not None:  # what the warm start had learned, this run knows too (policy.warm_start.learned)
            before = warm.pop("learned", {})
            for key in ("tasks", "instructions"):
                data_info[key] = sorted(set(data_info.get(key, [])) | set(before.get(key, [])))
            training["warm_start"] = {**warm, "learned_instructions": len(before.get("instructions", []))}
        if "gripper_levels" not in data_info:
            data_info["gripper_levels"] = list(_recorded_levels(run_dir, data_info.get("path")))
    check_phased(phased or [], data_info.get("tasks", []), "--phased")  # before minutes of measuring
    overrides = {k: v for k, v in (("inference_steps", inference_steps), ("noise_scale", noise_scale))
                 if v is not None}
    table, locator = None, None
    if goal_locator is not None and goal_query is None:
        raise ValueError("--goal-locator is what the goal query asks: give --goal-query FAMILY and --goal-query-data "
                         "too")
    if goal_query is not None:
        from policy.goal_query_measure import measure

        check_pace_table({f: 1.0 for f in goal_query["families"]}, data_info.get("tasks", []), "--goal-query")
        if goal_locator is not None:
            locator, record = load_locator(goal_locator, model.cfg)
        look = record.get("look_m") if locator is not None else None
        table = measure(model, normalizer, goal_query["data"], list(goal_query["families"]),
                        goal_query.get("ticks", 3), locator=locator, look=look)
        if locator is not None:
            table["locator_from"] = {"run": str(goal_locator), **record}
        overrides["release_input"] = True
    object_table, object_locator, turn_table, turn_model = None, None, None, None
    if queries_from is not None:
        if goal_query is not None and object_query is not None:
            raise ValueError("--queries-from keeps the bundle's queries this export does not measure anew; with both "
                             "--goal-query and --object-query there is none left to keep: drop --queries-from")
        anew = {"goal_query"} if goal_query is not None else {"object_query"} if object_query is not None else set()
        kept = _kept_queries(queries_from, model.cfg, data_info, anew)
        if goal_query is None:
            table, locator = kept[:2]
        object_table, object_locator, turn_table, turn_model = kept[2:]
        overrides.update(release_input=True, **({"grasp_input": True} if object_table else {}))
    if object_query is not None:
        object_table, object_locator = object_query_table(model.cfg, normalizer, object_query, data_info)
        overrides.update(release_input=True, grasp_input=True)
    if turn_locator is not None:
        turn_table, turn_model = turn_query_table(turn_locator, model.cfg, data_info.get("tasks", []))
    if object_table is not None:  # kept or measured, it serves the skill families of the ones it serves
        object_table = with_skill_families(object_table, data_info.get("tasks", []))
        if object_release_shift is not None:
            object_table["release_shift_m"] = list(check_release_shift(object_release_shift, "--object-release-shift"))
        if object_keep_release is not None:
            object_table["keep_release"] = list(check_keep_release(object_keep_release, object_table["families"],
                                                                   "--object-keep-release"))
    elif object_release_shift is not None or object_keep_release is not None:
        raise ValueError("--object-release-shift and --object-keep-release change the object query's release "
                         "point, and this export has no object query: give --object-query (or --queries-from a "
                         "bundle that asks one)")
    if overrides:
        model.cfg = load_policy_config(model.cfg, overrides)
    return export_model(model, normalizer, out_bundle_dir, data_info, training, opset, cache_dir, fp16_weights,
                        text_encoder_from, pace, table, locator, object_table, object_locator, phased,
                        turn_table, turn_model)


def _kept_queries(bundle_dir: str | Path, policy_cfg, data_info: dict, anew: set = frozenset()):
    """(goal table, goal locator, object table, object locator, turn table, turn locator) of a bundle, for
    `queries_from`; the queries in `anew` ("goal_query", "object_query") are measured by this export instead, so
    they come back None."""
    from policy.bundle_import import locator_from_bundle
    from policy.goal_locator import check_compatible

    source = json.loads((Path(bundle_dir) / "manifest.json").read_text())
    out: list = []
    for key, graph in (("goal_query", LOCATOR_GRAPH), ("object_query", OBJECT_GRAPH), ("turn_query", TURN_GRAPH)):
        table = source.get(key)
        if not table or key in anew:
            out += [None, None]
            continue
        if graph not in source.get("graphs", {}):
            raise ValueError(f"--queries-from {bundle_dir}: its {key} asks the policy's own head, which a new "
                             f"denoiser's run need not share; measure it again with --{key.replace('_', '-')}")
        missing = [f for f in table["families"] if f not in data_info.get("tasks", [])]
        if missing:
            raise ValueError(f"--queries-from {bundle_dir}: its {key} serves {', '.join(missing)}, which this run "
                             "was not trained on")
        locator, record = locator_from_bundle(bundle_dir, graph)
        check_compatible(policy_cfg, locator.cfg)
        out += [{**table, "kept_from": record}, locator]
    if all(t is None for t in out[::2]):
        kinds = [k.replace("_", " ") for k in ("goal_query", "object_query", "turn_query") if k not in anew]
        raise ValueError(f"--queries-from {bundle_dir}: the bundle asks no {' or '.join(kinds)} to keep")
    return tuple(out)


def _bundle_source(bundle_dir: Path):
    """(model, normalizer, data info, training record, its pace and phased records) of a bundle to export again."""
    from policy.bundle_import import model_from_bundle

    model, normalizer, m = model_from_bundle(bundle_dir)
    data_info = {"tasks": m.get("tasks", []), "instructions": m.get("instructions", []), **m.get("data", {})}
    training = {**m.get("training", {}), "reexported_from": {"bundle": str(bundle_dir), "created": m.get("created"),
                                                             "import": m["imported"]}}
    return model, normalizer, data_info, training, {"pace": m.get("pace", {}), "phased": m.get("phased", [])}


def _recorded_levels(run_dir: Path, data_path) -> tuple[float, ...]:
    """The gripper levels of a run trained before dataset.json recorded them, read from its data; without the
    data, a refusal: exported as open/closed only, a drawer policy's half-open pre-shape would never reach
    the fingers (runtime/controller/gripper.py)."""
    from datagen.schema import gripper_levels
    from datagen.store import Dataset

    if not data_path or not Path(data_path).is_dir():
        raise FileNotFoundError(f"{run_dir}/dataset.json records no gripper_levels and its data {data_path!r} is "
                                "gone: add \"gripper_levels\": [0.0, 1.0] there (or the levels the data's gripper "
                                "commands held, e.g. [0.0, 0.5, 1.0] with drawer episodes), or retrain")
    store = Dataset(data_path)
    return gripper_levels([store.window(row["index"], fields=("action",))["action"][:, -1] for row in store.episodes()])


def export_model(model: DiffusionPolicy, normalizer: Normalizer, out_bundle_dir: str | Path,
                 data_info: dict | None = None, training: dict | None = None, opset: int = OPSET,
                 cache_dir: str | Path | None = None, fp16_weights: bool = True,
                 text_encoder_from: str | Path | None = None, pace: dict[str, float] | None = None,
                 goal_query: dict | None = None, locator: DiffusionPolicy | None = None,
                 object_query: dict | None = None, object_locator: DiffusionPolicy | None = None,
                 phased: list[str] | None = None, turn_query: dict | None = None,
                 turn_locator: DiffusionPolicy | None = None) -> dict:
    """Write, verify and publish the bundle of `model` (atomically: a failed export leaves no bundle).
    goal_query: the manifest's table (policy.goal_query_measure), for a model with release_input; locator: the
    goal locator it was measured with (policy/goal_locator.py), written as goal_locator.onnx; object_query and
    object_locator: the same for the object query (policy/object_query.py; object_locator.onnx, grasp_input);
    turn_query and turn_locator for the turn query (policy/turn_query.py; turn_locator.onnx).

    fp16_weights: store the policy graphs' weights as float16; `model` itself is left unrounded."""
    import tokenizers

    from policy.fp16 import round_weights_
    from policy.text import MAX_SEQ_LENGTH
    from policy.text_export import add_text_encoder

    pace = check_pace_table(pace or {}, (data_info or {}).get("tasks", []), "--pace")  # before minutes of work
    phased = check_phased(phased or [], (data_info or {}).get("tasks", []), "--phased")
    model = model.eval().cpu()
    weights: dict = {"dtype": "float32"}
    if fp16_weights:  # the graphs then hold exactly this rounded model, so parity stays an exact check
        rounded = copy.deepcopy(model)
        round_weights_(rounded)
        weights = {"dtype": "float16", "rounding": rounding_cost(model, rounded, normalizer)}
        model = rounded
        locator, object_locator, turn_locator = _rounded(locator), _rounded(object_locator), _rounded(turn_locator)
    cfg = model.cfg
    out = Path(out_bundle_dir)
    if out.exists() and any(out.iterdir()) and not (out / "manifest.json").is_file():
        raise FileExistsError(f"{out} exists and is not a policy bundle; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.partial-"))
    try:
        specs = graph_specs(cfg)
        weights.update(write_policy_graphs(model, tmp, opset, fp16_weights))
        for graph, m in ((LOCATOR_GRAPH, locator), (OBJECT_GRAPH, object_locator), (TURN_GRAPH, turn_locator)):
            if m is not None:
                specs[graph] = locator_spec(cfg, graph)
                weights[graph] = _write_locator(m, tmp, specs[graph], opset, fp16_weights)
        text_info = add_text_encoder(tmp, cache_dir, opset, text_encoder_from)
        normalizer.save(tmp / "stats.npz")
        files = [p for p in sorted(tmp.rglob("*")) if p.is_file()]
        data_info = data_info or {}
        manifest = {
            "format": FORMAT, "format_version": FORMAT_VERSION, "opset": opset,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "producer": {"torch": torch.__version__, "tokenizers": tokenizers.__version__},
            "horizons": {"obs": cfg.obs_horizon, "pred": cfg.pred_horizon, "action": cfg.action_horizon,
                         "execute_from": cfg.obs_horizon - 1, "control_hz": 10.0},
            "dims": {"proprio": cfg.proprio_dim, "action": cfg.action_dim, "text": TEXT_DIM,
                     "instruction": cfg.text_input_dim, "cond": film_dim(cfg), "global_cond": cfg.global_cond_dim,
                     "stage_bins": cfg.stage_bins, **({"aux": cfg.aux_dim} if cfg.release_input else {})},
            "release_input": cfg.release_input, **({"grasp_input": True} if cfg.grasp_input else {}),
            "instruction": {"goal_clause": cfg.text_goal},
            "action_layout": {"position": [0, 3], "rot6d": [3, 9], "gripper": [9, 10], "frame": cfg.action_frame},
            "cameras": list(cfg.cameras), "image_size": list(cfg.image_size), "crop_size": list(cfg.crop_size),
            "graphs": specs,
            "tokenizer": {"dir": "tokenizer", "file": "tokenizer/tokenizer.json", "max_length": MAX_SEQ_LENGTH},
            "stats": {"file": "stats.npz", "keys": list(STAT_KEYS)},
            "diffusion": {"objective": cfg.objective, "num_train_timesteps": cfg.num_train_timesteps,
                          "beta_schedule": cfg.beta_schedule, "prediction_type": PREDICTS[cfg.objective],
                          "sampler": SAMPLER_KEY[cfg.objective], "eta": 0.0, "clip_sample": cfg.clip_sample,
                          "spacing": "trailing"},
            SAMPLER_KEY[cfg.objective]: schedule_for(model), "sampling": {"noise_scale": cfg.noise_scale},
            "tasks": data_info.get("tasks", []), "instructions": data_info.get("instructions", []),
            "pace": pace, **({"phased": list(phased)} if phased else {}),
            **({"goal_query": goal_query} if goal_query else {}),
            **({"object_query": object_query} if object_query else {}),
            **({"turn_query": turn_query} if turn_query else {}),
            "data": {k: v for k, v in data_info.items() if k not in ("tasks", "instructions")},
            "training": training or {}, "config": cfg.to_dict(),
            "params": {"obs_encoder": count_params(model.obs_encoder) + count_params(model.unet.film_cond)
                       + (count_params(model.aux_head) if cfg.aux_condition else 0),
                       "denoiser": count_params(model.unet) - count_params(model.unet.film_cond),
                       "policy_total": count_params(model), "text_encoder": text_info["params"]},
            "weights": weights, "text_encoder": text_info,
            "files": {str(p.relative_to(tmp)): {"bytes": p.stat().st_size, "sha256": sha256_file(p)} for p in files},
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        manifest["parity"] = check_parity(model, normalizer, tmp, locator=locator, object_locator=object_locator,
                                          turn_locator=turn_locator)
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest
