"""`sudd oracle-eval`: the closed-loop evaluation with the aux head's points replaced by the truth.

Why: a policy conditioned on its aux head's grasp and release points (`aux_condition`) fails either because the
head puts the points in the wrong place (perception) or because the denoiser does not take the gripper there
(control). This runs episodes exactly as `sudd eval` runs its seen suite (same seeds and scenes, the runtime's
controller and safety filter), but the denoiser is given the sim's true points: the named object's and its
bin's positions plus the median offsets at which the run's demonstrations close and open the gripper
(`datagen.views.measure_offsets`), in the TCP frame as training gives them. The grasp point follows the object
until it leaves the table, then stays where it was (the aux target is where the fingers closed).
`--bias-cm` moves the grasp point that far sideways, in a direction drawn per episode: how precisely
perception has to place it. `--true-points grasp` or `release` replaces only that point and leaves the other
the head's: which of the two the failures come from (a place missed beside the bin, a grasp missed beside
the object).

It runs the run's torch checkpoint (EMA weights), not the ONNX bundle, whose obs encoder fuses the head into the
denoiser's conditioning. That torch is why this lives in policy/ and not in runtime/.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

GRASP, RELEASE = 0, 1
TRUE_POINTS = {"both": (GRASP, RELEASE), "grasp": (GRASP,), "release": (RELEASE,)}  # --true-points: which are replaced
LIFTED_M = 0.01  # the object counts as taken once it is this far above where it started


def replaced_points(true_points: str) -> tuple[int, ...]:
    """--true-points -> the indices (GRASP, RELEASE) of the head's points the truth replaces."""
    if true_points not in TRUE_POINTS:
        raise ValueError(f"true_points {true_points!r}: expected one of {sorted(TRUE_POINTS)}")
    return TRUE_POINTS[true_points]


class TruePoints:
    """Observer for `run_policy_episode`: the episode's true grasp and release points (2, 3), base frame [m]."""

    def __init__(self, offsets: dict, bias_cm: float, seed: int, task: str = "pick_place"):
        from datagen.view_anchors import CARRIES

        self.picked, self.goal = CARRIES.get(task, ("target", None))
        self.offsets, self.points, self._z0 = offsets, None, None
        angle = np.random.default_rng([seed, 23]).uniform(0.0, 2 * np.pi)
        self.bias = bias_cm / 100.0 * np.array([np.cos(angle), np.sin(angle), 0.0])

    def __call__(self, world, inst) -> None:
        from sim.state import StateView

        state = StateView(world)
        obj, bin_ = state.position(inst.params[self.picked]), state.position(inst.params[self.goal])
        if self._z0 is None:
            self._z0 = obj[2]
        if self.points is None or obj[2] < self._z0 + LIFTED_M:
            self.points = np.stack([obj + self.offsets["grasp"] + self.bias, bin_ + self.offsets["release"]])


class DrawerPutPoints(TruePoints):
    """drawer_put's middle grasp cycle: the object (followed until lifted, as above) and the open drawer's floor
    (datagen.views_stages.drop_point, which moves with the drawer), the offsets measured on that cycle
    (`measure_offsets(data, "drawer_put/object")`) in the cabinet's frame."""

    def __call__(self, world, inst) -> None:
        from types import SimpleNamespace

        from datagen.views_stages import drop_point
        from sim.state import StateView
        from sim.tasks.drawer import CABINET

        state = StateView(world)
        R, obj = state.rotation(CABINET), state.position(inst.params[self.picked])
        if self._z0 is None:
            self._z0 = obj[2]
        grasp = obj + R @ self.offsets["grasp"] + self.bias
        if self.points is not None and obj[2] >= self._z0 + LIFTED_M:
            grasp = self.points[0]
        self.points = np.stack([grasp, drop_point(SimpleNamespace(world=world)) + R @ self.offsets["release"]])


class LocatedPoints:
    """drawer_put's middle grasp cycle's points as an object locator (policy/goal_locator.py, the "object" question)
    finds them: asked the command on the episode's first `ticks` frames (the arm at home, the drawer shut), the
    median of its answers (base frame) held for the rest, as the goal query does for stack. What a deployable
    drawer_put would be given in place of the truth."""

    def __init__(self, locator, command_embedding: np.ndarray, normalizer, ticks: int = 3):
        self.locator, self.embedding, self.normalizer, self.ticks = locator.eval(), command_embedding, normalizer, ticks
        self.answers: list[np.ndarray] = []
        self.points: np.ndarray | None = None

    def __call__(self, world, inst) -> None:  # an observer with nothing to follow: the answer is held
        pass

    def ask(self, images: dict, proprio: np.ndarray) -> None:
        """Ask the locator about this observation while fewer than `ticks` answers are in."""
        if len(self.answers) >= self.ticks:
            return
        import torch

        from policy.action_frame import points_from_tcp
        from policy.config import AUX_TCP_SCALE
        from policy.model import prepare_images

        cfg = self.locator.cfg
        with torch.no_grad():
            imgs = {c: prepare_images(torch.from_numpy(np.asarray(images[c]))[None], cfg.crop_size)
                    for c in cfg.cameras}
            p = torch.from_numpy(self.normalizer.normalize_proprio(proprio).astype(np.float32))[None]
            text = torch.from_numpy(np.asarray(self.embedding, np.float32))[None]
            pts = self.locator.aux_points(self.locator.obs_encoder(imgs, p, text))[0].numpy()
        grasp = points_from_tcp(pts[None, :3] * AUX_TCP_SCALE, np.asarray(proprio)[-1, :9])[0]
        self.answers.append(np.stack([grasp, pts[3:6] * AUX_TCP_SCALE]))
        self.points = np.median(np.stack(self.answers), axis=0)


class OracleAuxPolicy:
    """What `runtime.evaluate.run_policy_episode` needs of a bundle, from a torch run, with true aux points."""

    def __init__(self, model, normalizer, embedder, inference_steps: int | None = None, control_hz: float = 10.0,
                 true_points: str = "both", only_stage: int | None = None):
        cfg = model.cfg
        self.replaced = replaced_points(true_points)
        self.only_stage = only_stage  # replace the points only while this many grasp cycles are done (drawer_put: 1)
        if not cfg.aux_condition or cfg.aux_target_frame != "tcp" or cfg.action_frame != "tcp":
            raise ValueError("oracle-eval needs a run with aux_condition = true and the tcp aux target and action "
                             f"frames; this one has aux_condition={cfg.aux_condition}, aux_target_frame="
                             f"{cfg.aux_target_frame!r}, action_frame={cfg.action_frame!r}")
        self.model, self.normalizer, self._embedder = model.eval(), normalizer, embedder
        self.image_size, self.obs_horizon = tuple(cfg.image_size), cfg.obs_horizon
        self.pred_horizon, self.action_dim = cfg.pred_horizon, cfg.action_dim
        self.execute = slice(cfg.obs_horizon - 1, cfg.obs_horizon - 1 + cfg.action_horizon)
        self.manifest = {"horizons": {"control_hz": control_hz}}
        self.truth: TruePoints | None = None
        from policy.sampling import schedule_for

        self.schedule = schedule_for(model, inference_steps)

    def embed(self, text: str) -> np.ndarray:
        from policy.instruction import embed_instructions

        return embed_instructions(self._embedder, [text], self.model.cfg.text_goal)[0]

    def cond(self, images: dict, proprio: np.ndarray, text_embedding: np.ndarray, stage: int = 0):
        """The denoiser's global cond (1, G) with the aux head's points (those `true_points` names) replaced by
        the true ones (a grasp axis after them stays the head's)."""
        import torch

        from policy.data import relative_to_tcp
        from policy.model import prepare_images
        from policy.stage import with_stage

        cfg = self.model.cfg
        with torch.no_grad():
            imgs = {c: prepare_images(torch.from_numpy(np.asarray(images[c]))[None], cfg.crop_size)
                    for c in cfg.cameras}
            p = torch.from_numpy(with_stage(self.normalizer.normalize_proprio(proprio), stage, cfg.stage_bins))[None]
            cond = self.model.encode(imgs, p, torch.from_numpy(np.asarray(text_embedding, np.float32))[None])
        start = cond.shape[1] - cfg.aux_dim
        if isinstance(self.truth, LocatedPoints):
            self.truth.ask(images, proprio)
        true = relative_to_tcp(self.truth.points, np.asarray(proprio)[-1])
        for k in self.replaced if self.only_stage in (None, stage) else ():
            cond[0, start + 3 * k:start + 3 * k + 3] = true[3 * k:3 * k + 3]
        return cond

    def act(self, images, proprio, text_embedding, noise=None, rng=None, stage: int = 0) -> np.ndarray:
        import torch

        from policy.action_frame import from_tcp, orthonormalize_rot6d
        from policy.sampling import sample

        if noise is None:
            noise = (rng or np.random.default_rng()).standard_normal((self.pred_horizon, self.action_dim))
        cond = self.cond(images, proprio, text_embedding, stage)
        x = sample(self.model, cond, torch.from_numpy(np.asarray(noise, np.float32))[None], self.schedule)
        a = orthonormalize_rot6d(self.normalizer.unnormalize_action(x[0].numpy()))
        return from_tcp(a, np.asarray(proprio)[-1, :9])


_WORKER: dict = {}


def _init(settings: dict) -> None:
    import torch

    from policy.bundle_import import is_bundle, model_from_bundle
    from policy.text import default_embedder
    from policy.train import load_run_model
    from policy.warm_start import source_normalizer

    torch.set_num_threads(1)
    if is_bundle(settings["run"]):
        model, normalizer, _ = model_from_bundle(settings["run"])
    else:
        model, normalizer = load_run_model(settings["run"])[0], source_normalizer(settings["run"])
    policy = OracleAuxPolicy(model, normalizer, default_embedder(), settings["steps"],
                             true_points=settings["true_points"],
                             only_stage=1 if settings["task"] == "drawer_put" else None)
    # the gripper levels the controller snaps commands to, as `sudd eval` takes them from a bundle: without the
    # half-open 0.5 a drawer's handle is met with open fingers
    policy.manifest["data"] = {"gripper_levels": settings["gripper_levels"]}
    locator = None
    if settings.get("points_from"):
        from policy.goal_locator import load_locator

        locator = load_locator(settings["points_from"], model.cfg, "object")[0]
    _WORKER.update(settings=settings, policy=policy, locator=locator)


def _job(seed: int) -> dict:
    from policy.pace import Pace
    from runtime.evaluate import run_policy_episode
    from runtime.phases import phases_for
    from sim.tasks import Holdout

    s, policy = _WORKER["settings"], _WORKER["policy"]
    offsets = {k: np.asarray(v) for k, v in s["offsets"].items()}
    holdout = Holdout(colors=tuple(s["holdout"]["colors"]), shapes=tuple(s["holdout"]["shapes"]))
    if _WORKER["locator"] is not None:  # the command's object and drop as the locator finds them
        from sim.build import build_episode

        command = build_episode(s["task"], seed, s["dr"], "fast", holdout=holdout).instruction
        policy.truth = LocatedPoints(_WORKER["locator"], policy.embed(command), policy.normalizer)
    else:
        points = DrawerPutPoints if s["task"] == "drawer_put" else TruePoints
        policy.truth = points(offsets, s["bias_cm"], seed, s["task"])
    phases = phases_for(s["task"], Pace(s["pace"]), s["instructions"], s["tasks"]) if s["phases"] else None
    t0 = time.perf_counter()
    out = run_policy_episode(policy, s["task"], seed, dr=s["dr"], observer=policy.truth,
                             time_limit_factor=s["time_limit_factor"], latency_s=s["latency_s"], phases=phases,
                             holdout=holdout)
    suite = "oracle" if s["true_points"] == "both" else f"oracle-{s['true_points']}"
    suite = "located" if _WORKER["locator"] is not None else suite
    suite += "" if s["bias_cm"] == 0 else f"+{s['bias_cm']:g}cm"
    suite += "+phases" if s["phases"] else ""
    return {"suite": suite, "who": "policy", **out.record(), "wall_s": round(time.perf_counter() - t0, 2)}


def oracle_eval(run_dir: str | Path, out_dir: str | Path, episodes: int, seed_offset: int = 100000,
                bias_cm: float = 0.0, inference_steps: int | None = None, dr: str = "heavy", workers: int = 1,
                progress: bool = True, time_limit_factor: float = 1.0, true_points: str = "both",
                latency_ms: float | None = None, task: str = "pick_place", phases: bool = False,
                offsets_data: str | Path | None = None, points_from: str | Path | None = None) -> list[dict]:
    """Run the episodes, write results.jsonl and results.md to `out_dir`, return the summary rows.
    true_points: which aux points the truth replaces (TRUE_POINTS); latency_ms: a fixed simulated inference lag
    (as `sudd eval --latency-ms`: a rerun is then the same episodes) instead of each inference's measured one.
    task: a family that carries an object from a grasp to a release (datagen.view_anchors.CARRIES), or
    drawer_put, whose points are replaced in its middle grasp cycle only (the object to the drawer; opening and
    shutting keep the head's). phases: run the command as the skills of runtime.phases at the bundle's pace (a
    run has no pace table: 1). run_dir: a training run or a bundle (rebuilt in torch, policy.bundle_import);
    offsets_data: the dataset the grasp and release offsets are measured on (default the run's own).
    points_from: drawer_put only: an object locator run (`sudd pretrain --object-locator`) whose answers at the
    start (LocatedPoints) replace the truth: what the policy does with the points a deployable query gives."""
    replaced_points(true_points)  # a bad name fails here, before any worker starts
    if points_from is not None and (task != "drawer_put" or true_points != "both" or bias_cm):
        raise ValueError("--points-from gives drawer_put's object and drop as an object locator finds them: use it "
                         "with --task drawer_put, without --true-points or --bias-cm")
    from datagen.view_anchors import CARRIES
    from datagen.views import measure_offsets
    from policy.bundle_import import is_bundle
    from policy.pace import Pace, bundle_pace
    from runtime.eval_report import failure_table, markdown_table, summarise
    from runtime.phases import phases_for

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    if is_bundle(run_dir):
        manifest = json.loads((run_dir / "manifest.json").read_text())
        dataset, pace = manifest["data"], bundle_pace(manifest).table
        instructions, tasks = manifest.get("instructions") or [], manifest.get("tasks") or []
    else:
        dataset, pace = json.loads((run_dir / "dataset.json").read_text()), {}
        instructions, tasks = dataset.get("instructions") or [], dataset.get("tasks") or []
    if task not in (*CARRIES, "drawer_put"):
        raise ValueError(f"oracle-eval --task {task}: expected a family that carries an object, one of "
                         f"{', '.join(CARRIES)} or drawer_put (a drawer's points are its handle's, not an object's)")
    if phases:
        phases_for(task, Pace({}))  # a family run as one command fails here, before any worker starts
    offsets = measure_offsets(offsets_data or dataset["path"], "drawer_put/object" if task == "drawer_put" else task)
    settings = {"run": str(run_dir), "task": task, "phases": bool(phases), "pace": pace, "dr": dr,
                "instructions": list(instructions),  # a phase of its own text runs under it where taught
                "tasks": list(tasks),  # a phase another family's skill does runs as it where taught
                "bias_cm": float(bias_cm), "steps": inference_steps,
                "time_limit_factor": time_limit_factor, "true_points": true_points,
                "latency_s": None if latency_ms is None else latency_ms / 1000.0,
                "holdout": dataset.get("holdout") or {"colors": [], "shapes": []},
                "gripper_levels": dataset.get("gripper_levels"),
                "points_from": None if points_from is None else str(points_from),
                "offsets": {k: np.asarray(offsets[k]).tolist() for k in ("grasp", "release")}}
    seeds = list(range(seed_offset, seed_offset + episodes))
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    with open(out_dir / "results.jsonl", "w") as f:
        for rec in _map(seeds, settings, workers, progress):
            f.write(json.dumps(rec) + "\n")
            f.flush()  # an interrupted run keeps the episodes it finished
            records.append(rec)
    rows = summarise(records)
    (out_dir / "results.md").write_text(markdown_table(rows) + "\n\n" + failure_table(rows) + "\n")
    return rows


def _map(seeds: list[int], settings: dict, workers: int, progress: bool):
    from tqdm import tqdm

    bar = tqdm(total=len(seeds), desc="oracle-eval", unit="ep", disable=not progress)
    if workers <= 1:
        _init(settings)
        jobs = map(_job, seeds)
    else:
        import multiprocessing as mp

        pool = mp.get_context("spawn").Pool(workers, initializer=_init, initargs=(settings,))
        jobs = pool.imap_unordered(_job, seeds)
    ok = 0
    for rec in jobs:
        ok += bool(rec["success"])
        bar.update(1)
        bar.set_postfix(ok=ok)
        yield rec
    bar.close()
    if workers > 1:
        pool.close()
        pool.join()
