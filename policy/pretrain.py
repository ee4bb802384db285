"""Pretrain the policy's image encoders and aux head on rendered views (datagen.views): the aux loss alone.

Why: trained with the policy on a few hundred episodes, the encoders learn those scenes instead of where the
named object is (grasp point within 3 cm in training scenes, 8.5 cm off in new ones). Views are cheap, so
pretraining can show them thousands of scenes first. The policy run then starts from this one
(`sudd train --init-from PRETRAIN_RUN`) and learns its actions on the recorded episodes.

A view is one instant, while the policy sees To observation steps: each view fills all To steps (the arm at
rest, as at an episode's first step). Labels are the aux target of policy.data in the "tcp" frame (the
grasp and release points relative to the gripper, over AUX_TCP_SCALE), relabelled with the grasp and release
offsets measured on --data (datagen.views.load), so one set of views serves datasets whose demonstrations
grasp or release differently; with aux_grasp_axis the grasp-axis label follows them (policy/grasp_axis.py).
Augmentation is the policy's: one random crop per camera and sample, colour jitter.

The run directory is an ordinary one (config.json, stats.npz fitted on the episode dataset exactly as
training would fit it, dataset.json, checkpoints/, metrics.jsonl and metrics.png). With `val_fraction` > 0
it validates on that dataset's held-out episodes: `val_grasp_cm` is the head's median grasp-point error on
recorded frames of scenes neither the views nor training saw (the figure to compare with a policy run's).

`head_only` (with init_from) trains the aux head alone on frozen encoders. Why: continuing the whole pretraining
over approach and carrying views taught the release point while carrying (14.5 -> 6.7 cm) but moved the features
the grasp reads (grasp point before the grasp 2.35 -> 3.2 cm) and lost grasps; a policy trained with
freeze_pretrained feeds its denoiser true points in training and reads the head only at inference, so a head
retrained this way on the same encoders changes where the policy aims, not what it learnt. Measured from the
control's pretraining (3000 steps over approach + carrying views): release while carrying 14.5 -> 10.4 cm, but the
grasp point before the grasp 2.35 -> 4.4 cm: on features taught for the approach, the head's one hidden layer
cannot serve both points; the whole pretraining did better on both (6.7, 3.2 cm).

`episode_share` > 0 fills that share of every batch with recorded frames of --data's training episodes (the
policy's crop and jitter, the labels of policy.data), streamed from the store. Why: a view is a scene at rest,
rendered; a recorded frame mid-task is not (stack: the top block in the fingers above the others). The head
placed the block to stack on 3.5-4 cm off on stack views and 14 cm off on recorded carrying frames: it never saw
one. Validation stays on the held-out episodes.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from datagen.views import load as load_views
from datagen.views import measure_offsets
from datagen.views import tasks as view_tasks
from policy.config import PolicyConfig, load_policy_config
from policy.data import PolicyDataset, aux_point_target, color_jitter, crop, finish_images, jitter_factors
from policy.goal_locator import GRAPHS, check_question, locator_look, locator_rows
from policy.grasp_axis import axis_label, period_has_axis, turn_label, yaw_of
from policy.instruction import embed_instructions
from policy.model import DiffusionPolicy, count_params
from policy.plot import plot_metrics
from policy.ema import EMA
from policy.train import lr_factor, save_checkpoint
from policy import warm_start
from policy.validate import Validator
from policy.warm_start import PRETRAINED


class Views:
    """Rendered views as training batches (everything in memory, uint8 images)."""

    def __init__(self, views_dir: str | Path | list, cfg: PolicyConfig, normalizer, embedder,
                 offsets: dict | None = None, goal_locator: bool = False, question: str = "goal"):
        v = load_views(views_dir, offsets)
        if goal_locator:  # the home views, asked the locator's question (policy/goal_locator.py)
            v = locator_rows(v, question)
        self.families = sorted(set(v["task"].tolist()))
        if v["scene"].shape[1:3] != tuple(cfg.image_size):
            raise ValueError(f"{views_dir}: views are {v['scene'].shape[1:3]} pixels, the config expects "
                             f"{tuple(cfg.image_size)}; render them at the policy's image_size")
        self.cfg = cfg
        self.images = {c: v[c] for c in cfg.cameras}
        self.proprio = torch.from_numpy(normalizer.normalize_proprio(v["proprio"]).astype(np.float32))
        self.aux = torch.stack([aux_point_target(p, row, cfg.aux_release_frame)
                                for p, row in zip(v["points"], v["proprio"])])
        if cfg.aux_grasp_axis:
            if "grasp_yaw" not in v:
                raise ValueError(f"{views_dir}: aux_grasp_axis needs views that keep the grasp yaw, and (some of) "
                                 "these shards were rendered before it was kept; render them again with `sudd views`")
            tcp_yaw = yaw_of(v["proprio"][:, 3:9])
            axis = (turn_label(v["grasp_yaw"], tcp_yaw, v["footprint_period"]) if goal_locator and question == "turn"
                    else axis_label(v["grasp_yaw"], tcp_yaw, period_has_axis(v["footprint_period"])))
            self.aux = torch.cat([self.aux, torch.from_numpy(axis)], dim=1)
        texts = sorted(set(v["instruction"].tolist()))
        table = torch.from_numpy(embed_instructions(embedder, texts, cfg.text_goal))
        row = {t: k for k, t in enumerate(texts)}
        self.text = table[[row[t] for t in v["instruction"].tolist()]]
        self.scenes = int(len(np.unique(v["seed"])))
        self.look = locator_look(v) if goal_locator else None
        # the footprint period the turn question's answers are read for (locator_rows keeps views of one)
        self.period = float(v["footprint_period"][0]) if goal_locator and question == "turn" else None

    def __len__(self) -> int:
        return len(self.aux)

    def batch(self, rng: np.random.Generator, size: int) -> dict:
        cfg = self.cfg
        idx = rng.choice(len(self), size)
        H, W = cfg.image_size
        h, w = cfg.crop_size
        images = {}
        for c in cfg.cameras:
            frames = np.stack([crop(self.images[c][i], (h, w), int(rng.integers(0, H - h + 1)),
                                    int(rng.integers(0, W - w + 1))) for i in idx])
            x = torch.from_numpy(frames).permute(0, 3, 1, 2).float().div(255.0)
            x = x.unsqueeze(1).expand(-1, cfg.obs_horizon, -1, -1, -1)
            factors = torch.from_numpy(np.stack([jitter_factors(rng, cfg.color_jitter) for _ in idx]))
            images[c] = color_jitter(x, factors)
        proprio = self.proprio[idx].unsqueeze(1).expand(-1, cfg.obs_horizon, -1)
        return {"images": images, "proprio": proprio, "text": self.text[idx], "aux": self.aux[idx]}


class EpisodeFrames:
    """Training samples of recorded episodes as pretraining batches (the Views batch's keys), read per batch;
    with `tasks`, of those families only."""

    def __init__(self, ds: PolicyDataset, tasks: tuple[str, ...] = ()):
        self.ds = ds
        self.rows = np.array([i for i in range(len(ds)) if not tasks or ds.task_of(i) in tasks])
        if not len(self.rows):
            raise ValueError(f"no training samples of {', '.join(tasks)} in {ds.store.root}: "
                             f"the data has {', '.join(sorted(set(ds.tasks)))}")

    def batch(self, rng: np.random.Generator, size: int) -> dict:
        picks = self.rows[rng.integers(0, len(self.rows), size)]
        samples = [self.ds[(int(i), int(rng.integers(2 ** 31)))] for i in picks]
        b = finish_images({"images": {c: torch.stack([x["images"][c] for x in samples]) for c in self.ds.cfg.cameras},
                           "jitter": torch.stack([x["jitter"] for x in samples])})
        return {"images": b["images"], **{k: torch.stack([x[k] for x in samples]) for k in ("proprio", "text", "aux")}}


def mixed_batch(views: Views, episodes: EpisodeFrames | None, share: float, rng: np.random.Generator,
                size: int) -> dict:
    """`size` samples: round(share * size) from the episodes, the rest from the views."""
    n = round(share * size) if episodes is not None else 0
    b = views.batch(rng, size - n)
    if not n:
        return b
    e = episodes.batch(rng, n)
    return {"images": {c: torch.cat([b["images"][c], e["images"][c]]) for c in b["images"]},
            **{k: torch.cat([b[k], e[k]]) for k in ("proprio", "text", "aux")}}


def _names(views_dir) -> str | list[str]:
    return str(views_dir) if isinstance(views_dir, (str, Path)) else [str(d) for d in views_dir]


def pretrain(views_dir: str | Path | list, data_dir: str | Path, config: str | Path | PolicyConfig | dict,
             out_run_dir: str | Path, steps: int, overrides: dict | None = None, threads: int | None = None,
             progress: bool = True, embedder=None, init_from: str | Path | None = None,
             head_only: bool = False, episode_share: float = 0.0, episode_tasks: tuple[str, ...] = (),
             goal_locator: bool = False, locator_question: str = "goal", from_locator: bool = False) -> dict:
    """Train the encoders and aux head on the views for `steps` steps; returns the summary (see module doc).

    init_from: an earlier pretrain run to go on from (its EMA encoders and head, a fresh optimizer and
    schedule), for a longer pretraining without redoing the first part; or a policy bundle (policy/bundles/demo),
    to teach its encoders and head more families' views (the config must be the bundle's). Its --data may
    differ: the head reads the images and the instruction only, and the views are relabelled for this --data
    (module doc). The run keeps the source's normalization stats, which its encoders were trained with.
    head_only: train the aux head alone, the encoders as init_from left them (module doc).
    episode_share: the share of each batch taken from the data's training episodes (module doc), in [0, 1);
    episode_tasks: of these families only (default all).
    goal_locator: train a goal locator (policy/goal_locator.py) instead: the views at home, the swapped command, the
    release point as the grasp label and the loss on that point alone; validated by the goal query's error on
    --data's episodes (which the views never showed), before and during training, in place of the head's.
    locator_question: with goal_locator, "object" teaches the object question instead (policy/goal_locator.py:
    drawer_put's and drawer_stow's object and drop from the start, on `sudd views --at-home` views; the loss on the
    grasp and release points, validated by policy.goal_query_measure.measure_objects on --data's episodes of the
    views' families).
    from_locator: with goal_locator and a bundle as init_from, start from the bundle's own locator of that question
    (rebuilt from its graph) instead of its policy's encoders and head.
    """
    from tqdm import tqdm

    if threads:
        torch.set_num_threads(threads)
    cfg = load_policy_config(config, overrides)
    if cfg.aux_target_weight <= 0 or cfg.aux_target_frame != "tcp":
        raise ValueError("pretraining trains the aux head: it needs aux_target_weight > 0 and "
                         f"aux_target_frame 'tcp' (got {cfg.aux_target_weight}, {cfg.aux_target_frame!r})")
    if cfg.stage_bins:
        raise ValueError(f"stage_bins {cfg.stage_bins}: pretraining trains the encoders and head, which do not read "
                         "the grasp cycles; pretrain with stage_bins 0 and set it in `sudd train --init-from` (the "
                         "proprio encoder grows zero columns for it)")
    if not 0.0 <= episode_share < 1.0:
        raise ValueError(f"episode_share {episode_share}: expected a share of the batch in [0, 1) (the views fill "
                         "the rest; 0 = views only)")
    if episode_tasks and not episode_share:
        raise ValueError(f"episode_tasks {list(episode_tasks)} chooses the recorded frames of episode_share, which is 0: "
                         "give a share too (sudd pretrain --episode-share 0.25 --episode-task ...)")
    cols = check_question(locator_question) if goal_locator else slice(None)
    if goal_locator and locator_question == "turn" and not cfg.aux_grasp_axis:
        raise ValueError("the turn locator answers in the head's grasp-axis slot: it needs a policy with "
                         "aux_grasp_axis true (the bundle's config)")
    if goal_locator and (init_from is None or episode_share):
        raise ValueError("a goal locator is a copy of a policy's encoders and head taught the goal query on home views: "
                         "give --init-from the bundle it goes with, and no --episode-share (recorded frames carry "
                         "the policy's labels, not the query's)")
    if from_locator:
        from policy.bundle_import import is_bundle

        if not (goal_locator and init_from is not None and is_bundle(init_from)):
            raise ValueError("from_locator starts a locator from a bundle's own: give goal_locator (sudd pretrain "
                             f"--goal-locator or --object-locator) and init_from the bundle (--init-from BUNDLE; got "
                             f"{init_from})")
    if head_only and init_from is None:
        raise ValueError("head_only trains the aux head on the encoders of an earlier pretrain run: give init_from "
                         "(sudd pretrain --head-only --init-from PRETRAIN_RUN)")
    if embedder is None:
        from policy.text import default_embedder

        embedder = default_embedder()
    if init_from is not None:
        from policy.bundle_import import is_bundle

        if not (is_bundle(init_from) or warm_start.is_pretrain_run(init_from)):
            raise ValueError(f"--init-from {init_from}: neither a `sudd pretrain` run (its dataset.json has no "
                             "'pretrain') nor a policy bundle; go on from one of those, or start afresh")
    split = "train" if cfg.val_fraction > 0 else None
    fit = PolicyDataset(data_dir, cfg, train=False, embedder=embedder, uint8_images=True, split=split,
                        max_cache_bytes=0,
                        normalizer=None if init_from is None else warm_start.source_normalizer(init_from))
    validator = None
    if split and not goal_locator:
        val = PolicyDataset(data_dir, cfg, train=False, normalizer=fit.normalizer, embedder=embedder,
                            uint8_images=True, split="val", max_cache_bytes=0)
        validator = Validator(val, fit, seed=cfg.seed, chunks=False)
    offsets = {task: measure_offsets(data_dir, task) for task in view_tasks(views_dir)}
    views = Views(views_dir, cfg, fit.normalizer, embedder, offsets, goal_locator, locator_question)
    episodes = None
    if episode_share > 0:
        episodes = EpisodeFrames(PolicyDataset(data_dir, cfg, train=True, normalizer=fit.normalizer, embedder=embedder,
                                               uint8_images=True, split=split, max_cache_bytes=0),
                                 tuple(episode_tasks))
    torch.manual_seed(cfg.seed)
    model = DiffusionPolicy(cfg)
    model.set_proprio_stats(fit.normalizer)
    warm = None
    if from_locator:
        warm = warm_start.load_locator_into(model, init_from, GRAPHS[locator_question])
    elif init_from is not None:
        warm = warm_start.load_into(model, init_from)
    ema = EMA(model, cfg.ema_power, cfg.ema_max_decay)
    trained = ("aux_head",) if head_only else PRETRAINED
    params = [p for name in trained for p in model.get_submodule(name).parameters()]
    opt = torch.optim.AdamW(params, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: lr_factor(k, cfg.warmup_steps, steps))
    run_dir = Path(out_run_dir)
    if any(run_dir.glob("checkpoints/*.pt")) and not warm_start.is_pretrain_run(run_dir):
        raise FileExistsError(f"{run_dir} holds a policy run; pretraining would overwrite it: pick another --out")
    for old in run_dir.glob("checkpoints/*.pt"):  # a pretrain run is written afresh
        old.unlink()
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
    fit.normalizer.save(run_dir / "stats.npz")
    offsets_m = {t: {k: np.round(o[k], 4).tolist() for k in ("grasp", "release")} for t, o in offsets.items()}
    info = dict(fit.info(), pretrain={"views": _names(views_dir), "view_count": len(views), "scenes": views.scenes,
                                      "offsets_m": offsets_m, "head_only": head_only,
                                      "episode_share": episode_share, "episode_tasks": list(episode_tasks),
                                      "goal_locator": goal_locator,
                                      **({"locator_question": locator_question} if goal_locator else {}),
                                      **({"look_m": list(views.look)} if views.look else {}),
                                      **({"families": views.families, "data": str(data_dir),
                                          "period_deg": round(float(np.degrees(views.period)), 3)}
                                         if views.period else {})})
    (run_dir / "dataset.json").write_text(json.dumps(info, indent=2))
    if warm is not None:
        warm_start.write_record(run_dir, warm)
    metrics = run_dir / "metrics.jsonl"
    metrics.write_text("")
    rng = np.random.default_rng(cfg.seed)
    goal = None
    if goal_locator:
        goal = _locator_check(locator_question, fit.normalizer, data_dir, views.families, embedder, views.look,
                              views.period)
        with open(metrics, "a") as f:
            f.write(json.dumps({"step": 0, **goal(model)}) + "\n")
    model.train()
    acc, n_acc, t_log = 0.0, 0, time.perf_counter()
    for step in tqdm(range(1, steps + 1), desc="pretrain", unit="step", disable=not progress):
        b = mixed_batch(views, episodes, episode_share, rng, cfg.batch_size)
        with torch.set_grad_enabled(not head_only):  # frozen encoders: no backward through them
            features = model.obs_encoder(b["images"], b["proprio"], b["text"])
        loss = F.mse_loss(model.aux_points(features)[:, cols], b["aux"][:, cols])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        sched.step()
        ema.update(model)
        acc, n_acc = acc + float(loss.detach()), n_acc + 1
        with open(metrics, "a") as f:
            if step % cfg.log_every == 0 or step == steps:
                now = time.perf_counter()
                f.write(json.dumps({"step": step, "loss": acc / n_acc, "lr": sched.get_last_lr()[0],
                                    "steps_per_s": n_acc / (now - t_log)}) + "\n")
                acc, n_acc, t_log = 0.0, 0, now
            if validator is not None and (step % cfg.val_every == 0 or step == steps):
                f.write(json.dumps({"step": step, **validator(ema.model, torch.device("cpu"))}) + "\n")
            if goal is not None and (step % cfg.val_every == 0 or step == steps):
                f.write(json.dumps({"step": step, **goal(ema.model)}) + "\n")
    checkpoint = save_checkpoint(run_dir, steps, steps, model, ema, opt, sched, cfg)
    rows = [json.loads(x) for x in metrics.read_text().splitlines() if x.strip()]
    checks = [r for r in rows if "val_loss" in r or "goal_cm_median" in r or "object_grasp_cm_median" in r
              or "turn_deg_median" in r]
    losses = [r["loss"] for r in rows if "loss" in r]
    summary = {"run_dir": str(run_dir), "step": steps, "init_from": None if warm is None else warm["source"],
               "views": len(views), "scenes": views.scenes, "look_m": list(views.look) if views.look else None,
               "params": count_params(model), "checkpoint": str(checkpoint), "final_loss": losses[-1],
               "validation": checks[-1] if checks else None,
               **({"goal_query_before": checks[0]} if goal_locator else {}),
               "plot": str(plot_metrics(metrics, run_dir / "metrics.png"))}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _locator_check(question: str, normalizer, data_dir, families: list[str], embedder, look=None, period=None):
    """model -> the validation row of a locator of `question`: the goal query's error on --data's episodes
    (goal_cm_*), the object locator's grasp and release errors on the episodes of its views' families (object_*_cm_*
    for the first, object_FAMILY_*_cm_* for the others), or the turn locator's error on its family's recorded frames
    before the first close (turn_deg_*)."""
    from policy.goal_query_measure import measure, measure_objects

    if question == "turn":
        from policy.turn_query_measure import measure_turn

        family = families[0].partition("/")[0]
        return lambda m: {k: v for k, v in measure_turn(m.eval(), data_dir, family, period, embedder,
                                                        episodes=60).items()
                          if k.startswith(("turn", "no_turn", "sure"))}

    if question == "goal":
        def check(m) -> dict:
            q = measure(m.eval(), normalizer, data_dir, families, embedder=embedder, look=look)["measured"]
            return {"goal_cm_median": q["release_cm_median"], "goal_cm_p75": q["release_cm_p75"]}
        return check
    object_families = sorted({f.partition("/")[0] for f in families})

    def check_objects(m) -> dict:  # the first family's figures as object_*, each other's as object_FAMILY_*
        by_family = measure_objects(m.eval(), normalizer, data_dir, object_families, embedder=embedder)
        return {f"object_{'' if i == 0 else f + '_'}{k}": v for i, (f, q) in enumerate(by_family.items())
                for k, v in q.items() if k != "episodes"}
    return check_objects
