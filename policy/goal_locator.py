"""The goal locator: a copy of the policy's image encoders and aux head taught only the goal query's question,
so the query finds the object a command puts something on better than the policy's own head does.

Why: the goal query (policy/goal_query.py) asks the policy's head, on an episode's first frames (the arm at
home), where it would grasp if the command's two objects swapped roles. That head serves every family at every
pose of the approach and the carry, through one hidden layer: on 400 unseen stack episodes its answer is 3.8 cm
off the release point (median; p75 9.1 cm: a quarter of the answers are at the wrong block), where a block
let go more than ~2 cm off lands beside the one below. The question is always the same scene at the same pose,
so a copy of the encoders and head fine-tuned on that alone (rendered home views of the family, the swapped
command, the release point as the grasp label) answers it better. Measured (policy/EXPERIMENTS.md, "The goal
locator"): on those 400 episodes 2.3 cm (p75 4.8) after 5000 steps on 8000 home views of stack scenes; in closed
loop stack 44/100 against 38/100 on the same seeds (19 gained, 13 lost: not significant), the failures now mostly
let the block go within 2 cm of where it belongs. The policy's own encoders, head and denoiser are not touched
(their graphs stay byte for byte), so every other family acts as before.

Where it runs: `sudd pretrain VIEWS --data DATA --init-from BUNDLE --goal-locator` trains it (policy/pretrain.py,
with the rows and the loss here); `sudd export BUNDLE --goal-query stack --goal-query-data DATA --goal-locator
RUN` exports it as goal_locator.onnx (images and the instruction in, the head's points out; the manifest's
goal_query says "locator": true), and the bundle's `goal_point` reads it in place of the obs encoder's head.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from policy.goal_query import role_swap
from policy.turn_query import COLUMNS as TURN_COLUMNS  # the head's grasp-axis slot (aux_grasp_axis)
from policy.turn_query import GRAPH as TURN_GRAPH

GRAPH = "goal_locator"
FILE = "goal_locator.onnx"
OBJECT_GRAPH = "object_locator"  # the object question's locator (policy/object_query.py)
GOAL_COLUMNS = slice(0, 3)  # the head's grasp slot: the one point the goal query reads
# The question a locator is taught, and the head's columns its loss is on: "goal", the goal query's (the object a
# command puts something on, asked as the one to grasp: the grasp slot); "object", a long task's later grasp asked
# at the start (drawer_put: where the object is and where in the drawer it goes: the grasp and release slots);
# "turn", how far the wrist must turn to grasp the command's object, asked on the way there (the axis slot,
# policy.grasp_axis.turn_label).
QUESTIONS = {"goal": GOAL_COLUMNS, "object": slice(0, 6), "turn": TURN_COLUMNS}
GRAPHS = {"goal": GRAPH, "object": OBJECT_GRAPH, "turn": TURN_GRAPH}


def check_question(question: str) -> slice:
    """The loss columns of a locator `question` (QUESTIONS); a ValueError names the choices."""
    if question not in QUESTIONS:
        raise ValueError(f"locator question {question!r}: expected one of {', '.join(QUESTIONS)}")
    return QUESTIONS[question]


def _first_views(v: dict, home_stage: bool) -> np.ndarray:
    """Each scene's first view: of its first stage (home_stage False; a later stage's views set out from where the
    last release left the arm), or of an object's grasp rendered at home (`sudd views --at-home`: drawer_put's
    later stage, drawer_stow's first)."""
    n = len(v["instruction"])
    first = np.zeros(n, bool)
    at_home = v.get("at_home", np.zeros(n, bool))
    scene = list(zip(v["seed"].tolist(), [str(t) for t in v["task"]], [str(s) for s in v["stage"]]))
    seen: set = set()
    for i, key in enumerate(scene):
        wanted = bool(at_home[i]) if home_stage else not key[2] and not at_home[i]
        if key not in seen and wanted:
            seen.add(key)
            first[i] = True
    return first


def locator_rows(v: dict, question: str = "goal") -> dict:
    """Rendered views (datagen.views.load) relabelled for the locator's `question` (QUESTIONS): each scene's first
    view (the arm at home, where the question is asked). "goal": of the commands that name two objects, with the
    role-swapped command and the release point as the grasp label. "object": a later stage's views rendered at
    home, the command and the labels as they are. "turn": every view on the way to the first grasp (not only the
    first), as it is, of objects with one footprint period (the runtime reads the answers for that period). A
    ValueError when no view is of the kind."""
    check_question(question)
    n = len(v["instruction"])
    if question == "turn":  # every view on the way to the first grasp: the question is asked all along it
        keep = np.flatnonzero(np.array([not str(x) for x in v["stage"]], bool)
                              & ~np.asarray(v.get("at_home", np.zeros(n, bool)), bool))
        periods = np.unique(np.round(np.asarray(v.get("footprint_period", np.zeros(n)))[keep], 4))
        if not len(keep) or len(periods) != 1 or periods[0] <= 0:
            raise ValueError(f"the turn locator learns one footprint's turn: views of first grasps whose objects all "
                             f"have one footprint period (got periods {np.degrees(periods).round(1).tolist()} deg over "
                             f"{len(keep)} views); render views of one such family (sudd views --task stack)")
        return {k: (val[keep] if isinstance(val, np.ndarray) and len(val) == n else val) for k, val in v.items()}
    if question == "object":
        keep = np.flatnonzero(_first_views(v, home_stage=True))
        if not len(keep):
            raise ValueError("no home view of an object's grasp: the object locator learns drawer_put's and "
                             "drawer_stow's object from the start; render them with `sudd views --task drawer_put "
                             "--stage object --at-home` or `sudd views --task drawer_stow --at-home`")
        return {k: (val[keep] if isinstance(val, np.ndarray) and len(val) == n else val) for k, val in v.items()}
    first = _first_views(v, home_stage=False)
    swapped = [role_swap(str(t)) for t in v["instruction"]]
    keep = np.flatnonzero(first & np.array([s is not None for s in swapped], bool))
    if not len(keep):
        raise ValueError("no home view of a command that names two objects (policy.goal_query.role_swap): the goal "
                         "locator learns the swapped command; render views of such a family (sudd views --task stack)")
    out = {k: (val[keep] if isinstance(val, np.ndarray) and len(val) == n else val) for k, val in v.items()}
    out["instruction"] = np.array([swapped[i] for i in keep])
    points = np.array(out["points"], copy=True)
    points[:, 0] = points[:, 1]  # what the query reads as the grasp point is where the episode lets go
    out["points"] = points
    return out


def locator_look(rows: dict) -> tuple[float, float, float] | None:
    """The look offset the locator rows (`locator_rows`) were rendered from (`sudd views --look`), None for home;
    a ValueError where they mix poses: the locator has no proprio input, so it learns one pose's view."""
    looks = np.unique(np.round(np.asarray(rows.get("look", np.zeros((1, 3))), np.float64), 4), axis=0)
    if len(looks) != 1:
        raise ValueError(f"the locator's views were rendered from {len(looks)} poses ({looks.tolist()}): a locator "
                         "reads no proprio and answers from one pose; train it on views of one --look (or none)")
    look = tuple(float(v) for v in looks[0])
    return look if any(look) else None


class LocatorGraph(torch.nn.Module):
    """goal_locator.onnx: raw uint8 frames per camera and the instruction embedding -> the locator head's points
    (B, aux_dim), the grasp slot relative to the gripper over AUX_TCP_SCALE as the obs encoder's aux_points.
    The head reads the newest step's image features only, so no proprio goes in."""

    def __init__(self, model):
        super().__init__()
        self.model, self.cameras, self.crop = model, model.cfg.cameras, model.cfg.crop_size

    def forward(self, *args):
        from policy.model import prepare_images

        n = len(self.cameras)
        images = {c: prepare_images(x, self.crop) for c, x in zip(self.cameras, args[:n])}
        features = self.model.obs_encoder.camera_features(images, args[n])[:, -1]
        return self.model.aux_head(features)


def graph_spec(cfg, graph: str = GRAPH) -> dict:
    """The I/O of a locator graph, goal_locator.onnx or object_locator.onnx (as policy.bundle_manifest expects it)."""
    To, (H, W) = cfg.obs_horizon, cfg.image_size
    io = lambda n, s, d: {"name": n, "shape": s, "dtype": d}  # noqa: E731
    return {"file": f"{graph}.onnx",
            "inputs": [io(f"image_{c}", ["B", To, H, W, 3], "uint8") for c in cfg.cameras]
            + [io("text_embedding", ["B", cfg.text_input_dim], "float32")],
            "outputs": [io("aux_points", ["B", cfg.aux_dim], "float32")]}


def load_locator(run_dir: str | Path, policy_cfg, question: str = "goal"):
    """(model with EMA weights, its views record) of a `sudd pretrain --goal-locator` run (or `--object-locator`,
    `question` "object"), checked to read the policy's inputs and to have been taught that question."""
    from policy.train import load_run_model

    path = Path(run_dir) / "dataset.json"
    if not path.is_file():
        raise FileNotFoundError(f"--goal-locator {run_dir}: no dataset.json there; give a `sudd pretrain "
                                "--goal-locator` run directory")
    pre = json.loads(path.read_text()).get("pretrain") or {}
    if not pre.get("goal_locator"):
        raise ValueError(f"--goal-locator {run_dir}: not a goal locator run (its dataset.json's pretrain has no "
                         "goal_locator: true); train one with `sudd pretrain --goal-locator --init-from BUNDLE`")
    taught = pre.get("locator_question", "goal")  # runs from before the object question asked the goal's
    if taught != question:
        raise ValueError(f"{run_dir}: a locator taught the {taught} question, asked here the {question} question; "
                         f"give a `sudd pretrain --{question}-locator` run")
    locator, cfg, _ = load_run_model(run_dir)
    check_compatible(policy_cfg, cfg)
    return locator, {**{k: pre[k] for k in ("goal_locator", "locator_question", "views", "view_count", "scenes",
                                            "look_m") if k in pre}, "crop_size": list(cfg.crop_size)}


def check_compatible(policy_cfg, locator_cfg) -> None:
    """A locator must read the bundle's inputs: the same cameras, image size, horizon and instruction. Its crop may
    differ (the crop is inside its graph): a locator of the whole frame (`--set crop_size=[128,128]`) sees the
    block the wrist camera shows at its edge, which the policy's centre crop cuts off."""
    keys = ("cameras", "image_size", "obs_horizon", "text_goal", "aux_dim", "aux_target_frame")
    differ = [k for k in keys if getattr(policy_cfg, k) != getattr(locator_cfg, k)]
    if differ:
        raise ValueError("the goal locator reads other inputs than the policy: " + ", ".join(
            f"{k} {getattr(locator_cfg, k)!r} (policy {getattr(policy_cfg, k)!r})" for k in differ)
            + "; train it with `sudd pretrain --goal-locator --init-from` the bundle it goes with")


def object_query_table(policy_cfg, normalizer, request: dict, data_info: dict) -> tuple[dict, torch.nn.Module]:
    """(the manifest's object_query table, the locator) for `sudd export --object-query` (policy/object_query.py):
    request {"families", "data", "locator" (a `sudd pretrain --object-locator` run), "ticks"}; the locator's error
    measured on the data's episodes of each family it serves (policy.goal_query_measure.measure_objects), the
    skill families it serves too (policy.object_query.with_skill_families: drawer_stow) where the data has some."""
    from datagen.store import Dataset
    from datagen.views_stages import STAGES
    from policy.goal_query_measure import measure_objects
    from policy.object_query import with_skill_families

    families = list(request["families"])
    tasks = data_info.get("tasks", [])
    wrong = [f for f in families if f not in STAGES or f not in tasks]
    if wrong:
        raise ValueError(f"--object-query {', '.join(wrong)}: the object query serves a later grasp of a long task the "
                         f"policy was trained on ({', '.join(f for f in STAGES if f in tasks)})")
    locator, record = load_locator(request["locator"], policy_cfg, "object")
    ticks = int(request.get("ticks", 3))
    served = with_skill_families({"families": families}, tasks)["families"]
    recorded = {row["task"] for row in Dataset(request["data"]).episodes()}
    measured = measure_objects(locator, normalizer, request["data"],
                               [f for f in served if f in families or f in recorded], ticks)
    return {"families": families, "stage": 1, "ticks": ticks,
            "measured": {"data": str(request["data"]), "content_hash": Dataset(request["data"]).content_hash(),
                         "by_family": measured},
            "locator_from": {"run": str(request["locator"]), **record}}, locator
