"""A policy bundle's manifest contract (policy.export writes it, policy.bundle loads it): format, opsets, the
graph I/O its horizons and dims imply, and the self-consistency checks, each failure a BundleError with the reason.
numpy-free and torch-free."""

from __future__ import annotations

from policy.action_frame import FRAMES
from policy.goal_query import goal_query_spec
from policy.object_query import object_query_spec
from policy.pace import bundle_pace
from policy.phased import bundle_phased
from policy.turn_query import turn_query_spec

FORMAT = "sudd-policy-bundle"
SUPPORTED_VERSIONS = (1,)
SUPPORTED_OPSETS = range(13, 22)
TEXT_DIM = 384
STAT_KEYS = ("proprio_scale", "proprio_offset", "proprio_min", "proprio_max",
             "action_scale", "action_offset", "action_min", "action_max")


class BundleError(RuntimeError):
    """A policy bundle that must not be used; the message says which file or field and why."""


def goal_clause_of(m: dict) -> bool:
    """Whether the bundle reads the instruction as [sentence, goal clause] (policy.instruction); older: no."""
    return bool(m.get("instruction", {}).get("goal_clause", False))


def instruction_dim(m: dict) -> int:
    return TEXT_DIM * (2 if goal_clause_of(m) else 1)


def release_input_of(m: dict) -> bool:
    """Whether obs_encoder.onnx takes a release point and returns the head's points (policy/goal_query.py);
    bundles before it: no."""
    return bool(m.get("release_input", False))


def grasp_input_of(m: dict) -> bool:
    """Whether obs_encoder.onnx also takes a grasp point (policy/object_query.py); bundles before it: no."""
    return release_input_of(m) and bool(m.get("grasp_input", False))


def expected_graphs(m: dict) -> dict:
    """The graph I/O that the manifest's own horizons, dims, cameras and image size imply."""
    To, Tp = m["horizons"]["obs"], m["horizons"]["pred"]
    Dp, Da, G = m["dims"]["proprio"] + m["dims"].get("stage_bins", 0), m["dims"]["action"], m["dims"]["cond"]
    H, W = m["image_size"]
    io = lambda n, s, d: {"name": n, "shape": s, "dtype": d}  # noqa: E731
    release = (([io("release_point", ["B", 4], "float32")]
                + ([io("grasp_point", ["B", 4], "float32")] if grasp_input_of(m) else []),
                [io("aux_points", ["B", m["dims"].get("aux")], "float32")]) if release_input_of(m) else ([], []))
    images = [io(f"image_{c}", ["B", To, H, W, 3], "uint8") for c in m["cameras"]]
    text = io("text_embedding", ["B", instruction_dim(m)], "float32")
    locator = ({"goal_locator": {"inputs": images + [text], "outputs": release[1]}}
               if release_input_of(m) and (m.get("goal_query") or {}).get("locator") is True else {})
    if grasp_input_of(m) and m.get("object_query") is not None:  # its locator is the only way it is asked
        locator["object_locator"] = {"inputs": images + [text], "outputs": release[1]}
    if release_input_of(m) and m.get("turn_query") is not None:  # likewise (policy/turn_query.py)
        locator["turn_locator"] = {"inputs": images + [text], "outputs": release[1]}
    return {
        **locator,
        "obs_encoder": {"inputs": images + [io("proprio", ["B", To, Dp], "float32"), text] + release[0],
                        "outputs": [io("cond", ["B", G], "float32")] + release[1]},
        "denoiser": {"inputs": [io("noisy_actions", ["B", Tp, Da], "float32"), io("timestep", ["B"], "int64"),
                                io("cond", ["B", G], "float32")],
                     "outputs": [io("noise_pred", ["B", Tp, Da], "float32")]},
        "text_encoder": {"inputs": [io("input_ids", ["B", "L"], "int64"), io("attention_mask", ["B", "L"], "int64")],
                         "outputs": [io("embedding", ["B", TEXT_DIM], "float32")]},
    }


def need(ok: bool, msg: str) -> None:
    if not ok:
        raise BundleError(msg)


def check_manifest(m: dict) -> None:
    need(isinstance(m, dict) and m.get("format") == FORMAT, f"not a policy bundle (format={m.get('format')!r})")
    need(m.get("format_version") in SUPPORTED_VERSIONS, f"format_version {m.get('format_version')!r} is not "
          f"supported by this loader ({list(SUPPORTED_VERSIONS)}); re-export with a matching sudd")
    need(m.get("opset") in SUPPORTED_OPSETS, f"opset {m.get('opset')!r} is outside the supported "
          f"{SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1}")
    for key in ("horizons", "dims", "cameras", "image_size", "graphs", "stats", "tokenizer", "files"):
        need(key in m, f"manifest has no {key!r}")
    need(("ddim" in m) != ("euler" in m), "manifest needs exactly one sampler schedule, 'ddim' (DDPM) or 'euler' "
          f"(flow matching); it has {[k for k in ('ddim', 'euler') if k in m] or 'neither'}")
    h, d = m["horizons"], m["dims"]
    ints = [h.get("obs"), h.get("pred"), h.get("action"), h.get("execute_from"), d.get("proprio"), d.get("action"),
            d.get("cond"), d.get("stage_bins", 0), *m["image_size"]]
    need(all(isinstance(v, int) and v >= 0 for v in ints), f"horizons/dims/image_size must be integers: {ints}")
    need(0 < h["action"] and h["execute_from"] + h["action"] <= h["pred"] and h["execute_from"] < h["obs"],
          f"inconsistent horizons {h}")
    need(d.get("text") == TEXT_DIM and len(m["image_size"]) == 2 and m["cameras"], "bad text dim, image size or cameras")
    need(isinstance(m.get("instruction", {}).get("goal_clause", False), bool)
          and d.get("instruction", TEXT_DIM) == instruction_dim(m),
          f"dims.instruction {d.get('instruction')} does not match instruction {m.get('instruction')}: expected "
          f"{TEXT_DIM} (the sentence) or, with goal_clause true, {2 * TEXT_DIM}")
    frame = m.get("action_layout", {}).get("frame", "base")
    need(frame in FRAMES, f"action_layout frame {frame!r} is none of {list(FRAMES)}")
    if "ddim" in m:
        s = m["ddim"]
        ts, ab, abp = s.get("timesteps", []), s.get("alpha_bar", []), s.get("alpha_bar_prev", [])
        need(len(ts) > 0 and len(ts) == len(ab) == len(abp), "ddim schedule lists are empty or differ in length")
        need(all(0 < a <= 1 for a in ab + abp) and all(a > b for a, b in zip(ts, ts[1:])),
              "ddim schedule: alphas must lie in (0, 1] and timesteps descend")
    else:
        s = m["euler"]
        ts, sg, sgn = s.get("timesteps", []), s.get("sigma", []), s.get("sigma_next", [])
        need(len(ts) > 0 and len(ts) == len(sg) == len(sgn), "euler schedule lists are empty or differ in length")
        need(all(0 < a <= 1 for a in sg) and list(sgn) == list(sg[1:]) + [0.0]
              and all(a > b for a, b in zip(ts, ts[1:])),
              "euler schedule: noise levels must lie in (0, 1], descend to 0 and follow each other; timesteps descend")
    ns = m.get("sampling", {}).get("noise_scale", 1.0)
    need(isinstance(ns, (int, float)) and 0.0 <= ns <= 1.0, f"sampling noise_scale {ns!r} is outside [0, 1]")
    want = expected_graphs(m)
    for name, spec in want.items():
        got = m["graphs"].get(name, {})
        need(isinstance(got.get("file"), str), f"manifest graph {name!r} names no file")
        for kind in ("inputs", "outputs"):
            need(got.get(kind) == spec[kind], f"manifest graph {name} {kind} {got.get(kind)} do not follow from "
                  f"its horizons/dims/cameras (expected {spec[kind]})")
    for key in ("release_input", "grasp_input"):
        need(isinstance(m.get(key, False), bool), f"manifest {key} {m.get(key)!r}: expected true or false")
    need(release_input_of(m) or not m.get("grasp_input"), "manifest grasp_input needs release_input true (the obs "
         "encoder takes the grasp point beside the release point)")
    if release_input_of(m):
        aux = m["dims"].get("aux")
        need(isinstance(aux, int) and aux >= 6, f"dims.aux {aux!r}: a bundle with release_input needs the aux "
              "head's width, an integer >= 6 (grasp and release points)")
    try:
        bundle_pace(m)
        bundle_phased(m)
        goal_query_spec(m)
        object_query_spec(m)
        turn_query_spec(m)
    except ValueError as exc:
        raise BundleError(str(exc)) from None
    te = m.get("text_encoder", {})
    if te.get("restorable"):
        ref = te.get("reference", {})
        need(set(te.get("files", [])) <= set(m["files"]) and ref.get("file") in set(m["files"]) - set(te["files"])
              and ref.get("sentences") and isinstance(ref.get("min_cosine"), float),
              "manifest text_encoder: restorable files and a hashed reference of sentences + min_cosine are needed")
