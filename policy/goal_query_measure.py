"""The goal query's offset and its error, measured on recorded episodes when a bundle is exported
(`sudd export ... --goal-query FAMILY --goal-query-data DATA`); the query itself is policy/goal_query.py.

For every verified episode of the families whose command names two objects, the torch policy's head is asked
the role-swapped command about the episode's first `ticks` frames, as the runtime asks it, and the median of
its grasp points (base frame) is compared with the recorded release point: the offset is the median of
(release - that point) over the episodes. Its error is measured two-fold (the offset fitted on every other
episode and scored on the rest, then the other way), against the head's own release point on the same frames,
so the manifest says what the query buys on episodes the offset was not fitted on. Measure on data the policy
did not train on: a head grounds the scenes it trained on better than new ones.

`measure_object` scores an object locator (policy/goal_locator.py, the "object" question) the same way: its grasp
and release points on the first frames of a long task's episodes against the recorded later cycle's.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import default_collate

from policy.action_frame import points_from_tcp
from policy.config import AUX_TCP_SCALE
from policy.goal_query import MAX_OFFSET_M, MAX_TICKS, role_swap
from policy.instruction import embed_instructions


@torch.no_grad()
def measure(model, normalizer, data, families: list[str], ticks: int = 3, embedder=None, locator=None,
            look=None) -> dict:
    """The manifest's goal_query table for `model` on `data` (module doc); a ValueError when no episode of
    `families` has a command with two objects. locator: a goal locator (policy/goal_locator.py) asked the swapped
    command in place of `model`'s head; the head's own release point is still `model`'s. look: the locator asks
    from the start pose moved this far (`sudd views --look`); the recorded episodes never stood there, so each
    episode's scene is rendered from that pose (datagen.views.look_view: the same seed, the same scene)."""
    from policy.data import finish_images

    if not 1 <= int(ticks) <= MAX_TICKS:
        raise ValueError(f"goal query ticks {ticks}: expected an integer in [1, {MAX_TICKS}]")
    cfg = model.cfg
    if not (cfg.aux_condition and cfg.aux_release_frame == "base" and cfg.aux_target_frame == "tcp"):
        raise ValueError("the goal query replaces the head's base-frame release point: it needs a policy with "
                         f"aux_condition, aux_release_frame 'base' and aux_target_frame 'tcp' (this one: "
                         f"{cfg.aux_condition}, {cfg.aux_release_frame!r}, {cfg.aux_target_frame!r})")
    embedder = _embedder(embedder)
    ds, first = _first_frames(data, cfg, normalizer, embedder, ticks,
                              lambda ds, k: ds.tasks[k] in families and role_swap(ds.instructions[k]))
    if not first:
        raise ValueError(f"{data}: no verified episode of {', '.join(families)} whose command names two objects "
                         "(policy.goal_query.role_swap); measure on data of those families")
    model.eval()
    asked = model if locator is None else locator.eval()
    # the frames as the asked model crops them: a locator may read the whole frame (goal_locator.check_compatible)
    asked_ds = ds if asked.cfg.crop_size == cfg.crop_size else _dataset(data, asked.cfg, normalizer, embedder)
    queried, head_release, truth = [], [], []
    for k, rows in sorted(first.items()):
        batch = finish_images(default_collate([ds[i] for i in rows]))
        asked_batch = batch if asked_ds is ds else finish_images(default_collate([asked_ds[i] for i in rows]))
        swapped = torch.from_numpy(embed_instructions(embedder, [role_swap(ds.instructions[k])], cfg.text_goal))
        own = model.aux_points(model.obs_encoder(batch["images"], batch["proprio"], batch["text"]))[:, 3:6].numpy()
        steps = [ds._newest_step(i)[1] for i in rows]
        if look is None:
            grasp = asked.aux_points(asked.obs_encoder(asked_batch["images"], asked_batch["proprio"],
                                                       swapped.expand(len(rows), -1)))[:, :3].numpy()
            poses = np.stack([ds.tcp_pose[k][t][:9] for t in steps])
        else:
            grasp, poses = _asked_from_look(asked, ds.store.meta(ds.episodes[k]), look, swapped)
        queried.append(np.median(points_from_tcp(grasp[:, None] * AUX_TCP_SCALE, poses)[:, 0], axis=0))
        head_release.append(np.median(own * AUX_TCP_SCALE, axis=0))
        truth.append(ds.aux_points[k][steps[0]][1])
    queried, head_release, truth = np.stack(queried), np.stack(head_release), np.stack(truth)
    offset = np.median(truth - queried, axis=0)
    if float(np.linalg.norm(offset)) > MAX_OFFSET_M:
        raise ValueError(f"goal query offset {np.round(offset, 3).tolist()} m is longer than {MAX_OFFSET_M} m: the "
                         "head's swapped grasp points are not near the release points; no goal query for this policy")
    halves = np.arange(len(truth)) % 2 == 0
    errors = np.empty(len(truth))
    for fit in (halves, ~halves):  # two-fold: each half scored with the offset of the other
        errors[~fit] = np.linalg.norm(queried[~fit] + np.median(truth[fit] - queried[fit], axis=0) - truth[~fit], axis=1)
    head = np.linalg.norm(head_release - truth, axis=1)
    from datagen.store import Dataset

    return {"families": list(families), "offset_m": [round(float(v), 4) for v in offset], "ticks": int(ticks),
            **({"locator": True} if locator is not None else {}),
            **({"look_m": [round(float(v), 4) for v in look]} if look is not None else {}),
            "measured": {"data": str(data), "content_hash": Dataset(data).content_hash(), "episodes": len(truth),
                         "release_cm_median": round(float(np.median(errors)) * 100, 2),
                         "release_cm_p75": round(float(np.percentile(errors, 75)) * 100, 2),
                         "head_release_cm_median": round(float(np.median(head)) * 100, 2),
                         "head_release_cm_p75": round(float(np.percentile(head, 75)) * 100, 2)}}


@torch.no_grad()
def measure_object(locator, normalizer, data, family: str = "drawer_put", stage: int = 1, ticks: int = 3,
                   embedder=None) -> dict:
    """How far an object locator (policy/goal_locator.py, question "object") is off a long task's later grasp
    cycle, asked the command on each verified `family` episode's first `ticks` frames (the arm at home) as the
    query would be: the median of its grasp points (base frame) against the recorded grasp of cycle `stage` (the
    object), of its release points against that cycle's release (the drop in the drawer), on the episodes that made
    exactly one cycle per stage (a retry's extra one would shift the count). A ValueError when there is none."""
    from datagen.views_stages import stages
    from policy.data import finish_images

    ds, first = _first_frames(data, locator.cfg, normalizer, _embedder(embedder), ticks,
                              lambda ds, k: ds.tasks[k] == family)
    grasp_err, release_err = [], []
    for k, rows in sorted(first.items()):
        cycles, at = np.unique(ds.cycle[k], axis=0, return_index=True)
        if len(cycles) != len(stages(family)):
            continue
        truth = ds.aux_points[k][sorted(at)[stage]]  # (2, 3): that cycle's grasp and release, base frame [m]
        batch = finish_images(default_collate([ds[i] for i in rows]))
        points = locator.eval().aux_points(locator.obs_encoder(batch["images"], batch["proprio"], batch["text"]))
        poses = np.stack([ds.tcp_pose[k][ds._newest_step(i)[1]][:9] for i in rows])
        grasp = points_from_tcp(points[:, None, :3].numpy() * AUX_TCP_SCALE, poses)[:, 0]
        release = points[:, 3:6].numpy() * AUX_TCP_SCALE
        grasp_err.append(np.linalg.norm(np.median(grasp, axis=0) - truth[0]))
        release_err.append(np.linalg.norm(np.median(release, axis=0) - truth[1]))
    if not grasp_err:
        raise ValueError(f"{data}: no verified {family} episode with one grasp cycle per stage to measure the object "
                         f"locator on; record some (sudd datagen --task {family})")
    cm = lambda e, q: round(float(np.percentile(e, q)) * 100, 2)  # noqa: E731
    return {"episodes": len(grasp_err), "grasp_cm_median": cm(grasp_err, 50), "grasp_cm_p75": cm(grasp_err, 75),
            "release_cm_median": cm(release_err, 50), "release_cm_p75": cm(release_err, 75)}


def measure_objects(locator, normalizer, data, families, ticks: int = 3, embedder=None) -> dict:
    """measure_object for each of `families` at the grasp cycle its object is taken in (datagen.views_stages
    .OBJECT_AT_START: drawer_put's second, drawer_stow's first): {family: its figures}."""
    from datagen.views_stages import OBJECT_AT_START

    unknown = [f for f in families if f not in OBJECT_AT_START]
    if unknown:
        raise ValueError(f"the object locator answers {', '.join(OBJECT_AT_START)}, not {', '.join(unknown)}")
    return {f: measure_object(locator, normalizer, data, f, OBJECT_AT_START[f], ticks, embedder) for f in families}


def _asked_from_look(locator, meta: dict, look, text: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(the locator's grasp points (1, 3) TCP-relative over AUX_TCP_SCALE, the TCP poses (1, 9)) for the recorded
    episode `meta`'s scene seen from the look pose, through the graph the bundle exports (LocatorGraph)."""
    from datagen.views import look_view
    from policy.goal_locator import LocatorGraph
    from sim.tasks import Holdout

    h = meta.get("holdout") or {}
    images, proprio = look_view(meta["task"], int(meta["seed"]), look,
                                Holdout(tuple(h.get("colors", ())), tuple(h.get("shapes", ()))),
                                meta.get("fidelity") or "fast", image_size=tuple(locator.cfg.image_size))
    To = locator.cfg.obs_horizon
    frames = [torch.from_numpy(np.repeat(images[c][None, -1:], To, axis=1)) for c in locator.cfg.cameras]
    points = LocatorGraph(locator.eval())(*frames, text)
    return points[:, :3].numpy(), proprio[-1:, :9].astype(np.float64)


def _first_frames(data, cfg, normalizer, embedder, ticks: int, keep) -> tuple:
    """(the dataset of `data` as `cfg` reads it, {episode: its samples whose newest frame is one of the first
    `ticks`}) for the episodes `keep(ds, k)` accepts: the frames a query at the start is asked about."""
    ds = _dataset(data, cfg, normalizer, embedder)
    first: dict[int, list[int]] = {}
    for i, (k, s) in enumerate(ds.index):
        if 0 <= s + cfg.obs_horizon - 1 < ticks and keep(ds, k):
            first.setdefault(k, []).append(i)
    return ds, first


def _dataset(data, cfg, normalizer, embedder):
    """`data`'s samples as `cfg` reads them (its crop, its horizon), unaugmented, images as uint8."""
    from policy.data import PolicyDataset

    return PolicyDataset(data, cfg, train=False, normalizer=normalizer, embedder=embedder, uint8_images=True,
                         max_cache_bytes=0)


def _embedder(embedder):
    """The sentence encoder to embed commands with: the one given, else the default (MiniLM)."""
    if embedder is not None:
        return embedder
    from policy.text import default_embedder

    return default_embedder()
