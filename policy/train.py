"""Training: DDPM epsilon-prediction loss, AdamW + warm-up/cosine, EMA, checkpoints, resume, DDP.

    train(data_dir, "small", "runs/pp", steps=2000)                       # one process
    torchrun --standalone --nproc_per_node 2 -m policy.train DATA RUN --steps 2000   # DDP (gloo on CPU)

Run directory: config.json, stats.npz (normalization, fixed at the first start), dataset.json (content hash,
tasks, instructions), environment.json (the CPU and versions it started on), metrics.jsonl (step, loss, lr,
steps/s), metrics.png, summary.json, checkpoints/step_XXXXXXXX.pt (model, EMA, optimizer, scheduler; the last
`keep_checkpoints`).

Reproducibility: every random draw of step k (which samples, their crops and jitter, the diffusion noise
and timesteps) is a function of (seed, k, rank) only - not of the state of a generator that ran before.
So a run resumed from its last checkpoint replays exactly what an uninterrupted run would have done
(tested: same weights within float tolerance), whatever the interruption point and with any worker count,
on the machine it started on (another CPU's kernels may round otherwise), which RUN/environment.json records.

DDP: each process loads the dataset, takes its share of every epoch's permutation (rank::world) at
`batch_size` per process, and averages gradients (NCCL on GPUs, gloo on CPU). Rank 0 alone writes files.
At the end the replicas' weights are compared (max difference recorded in summary.json; it must be 0).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Sampler
from torch.utils.data._utils.collate import default_collate

from policy import warm_start
from policy.ema import EMA
from policy.config import PolicyConfig, config_from_dict, load_policy_config
from policy.data import PolicyDataset, finish_images, to_device
from policy.feature_cache import image_feature_table
from policy.model import DiffusionPolicy, count_params
from policy.normalize import Normalizer
from policy.plot import plot_metrics
from policy.validate import Validator
from runtime.machine_record import TRAIN_PACKAGES, environment_change


def resolve_device(device: str = "auto") -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def seed_everything(seed: int) -> None:
    import random

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def step_seed(seed: int, step: int, rank: int, stream: int) -> int:
    return int(np.random.SeedSequence([seed, step, rank, stream]).generate_state(1)[0])


def lr_factor(step: int, warmup: int, total: int) -> float:
    """Linear warm-up to 1, then cosine decay to 0 at `total`."""
    if step < warmup:
        return (step + 1) / warmup
    return 0.5 * (1 + math.cos(math.pi * min(1.0, (step - warmup) / max(1, total - warmup))))


class StepBatches(Sampler):
    """Batches of (sample index, augmentation seed) for steps [start, stop): a pure function of the step."""

    def __init__(self, n: int, batch: int, seed: int, rank: int, world: int, start: int, stop: int):
        self.n, self.batch, self.seed, self.rank, self.world = n, batch, seed, rank, world
        self.start, self.stop = start, stop
        self.per_epoch = max(1, n // (batch * world))

    def plan(self, step: int) -> list[tuple[int, int]]:
        epoch, j = divmod(step, self.per_epoch)
        perm = np.random.default_rng([self.seed, epoch]).permutation(self.n)
        need = self.per_epoch * self.batch * self.world
        perm = np.resize(perm, max(need, self.n))  # a dataset smaller than one global batch repeats
        lo = (j * self.world + self.rank) * self.batch
        seeds = np.random.SeedSequence([self.seed, step, self.rank, 0]).generate_state(self.batch)
        return [(int(i), int(s)) for i, s in zip(perm[lo:lo + self.batch], seeds)]

    def __iter__(self):
        return (self.plan(k) for k in range(self.start, self.stop))

    def __len__(self) -> int:
        return self.stop - self.start


def _checkpoints(run_dir: Path) -> list[Path]:
    return sorted((run_dir / "checkpoints").glob("step_*.pt"))


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    found = _checkpoints(Path(run_dir))
    return found[-1] if found else None


def load_run_model(run_dir: str | Path, checkpoint: str | Path | None = None, ema: bool = True
                   ) -> tuple[DiffusionPolicy, PolicyConfig, dict]:
    """The trained policy (EMA weights by default) of a run, its config and the checkpoint's step info."""
    run_dir = Path(run_dir)
    path = Path(checkpoint) if checkpoint else latest_checkpoint(run_dir)
    if path is None:
        raise FileNotFoundError(f"{run_dir} has no checkpoint (checkpoints/step_*.pt)")
    state = torch.load(path, map_location="cpu", weights_only=False)
    cfg = config_from_dict(state["config"])
    model = DiffusionPolicy(cfg)
    model.load_state_dict(state["ema"]["model"] if ema else state["model"])
    return model.eval(), cfg, {"step": state["step"], "checkpoint": str(path), "ema": ema}


def save_checkpoint(run_dir: Path, step: int, total: int, model, ema: EMA, opt, sched,
                    cfg: PolicyConfig) -> Path:
    ckpt_dir = run_dir / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    path = ckpt_dir / f"step_{step:08d}.pt"
    tmp = path.with_suffix(".tmp")
    torch.save({"step": step, "total_steps": total, "model": model.state_dict(), "ema": ema.state_dict(),
                "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "config": cfg.to_dict(),
                "torch": torch.__version__}, tmp)
    os.replace(tmp, path)  # atomic: a kill leaves the previous checkpoint intact
    for old in _checkpoints(run_dir)[:-cfg.keep_checkpoints]:
        old.unlink(missing_ok=True)
    return path


def _dist_setup(device: str) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        local = int(os.environ.get("LOCAL_RANK", "0"))
        dev = resolve_device(device)
        if dev.type == "cuda":
            dev = torch.device("cuda", local)
            torch.cuda.set_device(dev)
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
        return dist.get_rank(), world, dev
    return (dist.get_rank() if dist.is_initialized() else 0), world, resolve_device(device)


def train(data_dir: str | Path, config: str | Path | PolicyConfig | dict = "small", out_run_dir: str | Path = "runs/policy",
          steps: int | None = None, epochs: int | None = None, resume: bool = True, device: str = "auto",
          progress: bool = True, stop_at: int | None = None, embedder=None, overrides: dict | None = None,
          threads: int | None = None, init_from: str | Path | None = None,
          encoders_from: str | Path | None = None) -> dict:
    """Train (or resume) a policy run; returns the summary (also written to RUN/summary.json).

    steps or epochs sets the schedule's length (an epoch = one pass over the samples by all processes).
    stop_at: leave after that step with a checkpoint, as a preemption would (resume continues the same run).
    threads: torch intra-op threads (None: torch's default). On a shared 2-core machine 1 is faster for
    small models: two spinning OpenMP threads stall whenever the OS deschedules one of them.
    init_from: a trained run to warm-start a fresh run from (policy.warm_start); ignored when resuming.
    encoders_from: with init_from, a `sudd pretrain` run whose image encoders and aux head replace init_from's.
    """
    if encoders_from is not None and init_from is None:
        raise ValueError("encoders_from (--encoders-from) replaces the encoders of the run given by init_from "
                         "(--init-from): give both")
    if threads:
        torch.set_num_threads(threads)
    # DDP notes that 1x1 conv weight grads have different (equivalent) strides than its buckets: harmless
    warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
    cfg = load_policy_config(config, overrides)
    rank, world, dev = _dist_setup(device)
    run_dir = Path(out_run_dir)
    seed_everything(cfg.seed)
    ckpt = latest_checkpoint(run_dir) if resume else None
    if ckpt is None and resume is False and rank == 0 and (run_dir / "checkpoints").is_dir():
        for old in _checkpoints(run_dir):
            old.unlink()
    normalizer = None
    if ckpt is not None:
        recorded = config_from_dict(json.loads((run_dir / "config.json").read_text()))
        if recorded != cfg:
            raise ValueError(f"{run_dir} was started with another config; resume=False starts it afresh")
        normalizer = Normalizer.load(run_dir / "stats.npz")
    elif init_from is not None:
        normalizer = warm_start.source_normalizer(init_from)
    split = "train" if cfg.val_fraction > 0 else None
    ds = PolicyDataset(data_dir, cfg, train=True, normalizer=normalizer, embedder=embedder, uint8_images=True,
                       split=split, read_images=not cfg.feature_cache)
    info = ds.info()
    validator = None
    if split and rank == 0:  # streamed from the store (max_cache_bytes=0): a few hundred samples per check
        sets = [PolicyDataset(data_dir, cfg, train=False, normalizer=ds.normalizer, embedder=embedder,
                              uint8_images=True, split=s, max_cache_bytes=0) for s in ("val", "train")]
        validator = Validator(*sets, seed=cfg.seed)
        info["validation_episodes"] = len(sets[0].episodes)
    if ckpt is not None:
        old = json.loads((run_dir / "dataset.json").read_text())["content_hash"]
        if old != info["content_hash"]:
            raise ValueError(f"{data_dir} changed since {run_dir} started (content hash {old[:12]} -> "
                             f"{info['content_hash'][:12]}); resume=False starts the run afresh")
    batches = StepBatches(len(ds), cfg.batch_size, cfg.seed, rank, world, 0, 0)
    total = steps if steps is not None else (epochs or 1) * batches.per_epoch

    model = DiffusionPolicy(cfg)
    model.set_proprio_stats(ds.normalizer)
    warm = warm_start.load_into(model, init_from) if ckpt is None and init_from is not None else None
    if warm is not None and encoders_from is not None:
        warm["encoders"] = warm_start.load_pretrained_into(model, encoders_from, ds.normalizer)
    if cfg.freeze_pretrained:
        if ckpt is None and init_from is None:
            raise ValueError("freeze_pretrained keeps the image encoders and aux head as initialized: start the "
                             "run with init_from (--init-from RUN, a `sudd pretrain` run), or leave it false")
        for name in warm_start.PRETRAINED:
            if not (name == "aux_head" and cfg.train_aux_head):
                model.get_submodule(name).requires_grad_(False)
    model = model.to(dev)
    table = None
    if cfg.feature_cache:  # the frozen encoders' output, once (policy.feature_cache)
        table = image_feature_table(model, ds, cfg.feature_cache, seed=cfg.seed, device=dev,
                                    progress=progress and rank == 0)
    ema = EMA(model, cfg.ema_power, cfg.ema_max_decay)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.lr, betas=cfg.betas,
                            weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: lr_factor(k, cfg.warmup_steps, total))
    start = 0
    if ckpt is not None:
        state = torch.load(ckpt, map_location=dev, weights_only=False)
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        start = state["step"]
    net = _Loss(model)
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(net, device_ids=[dev.index] if dev.type == "cuda" else None)
    if rank == 0:
        run_dir.mkdir(parents=True, exist_ok=True)
        if ckpt is None:
            (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
            ds.normalizer.save(run_dir / "stats.npz")
            (run_dir / "dataset.json").write_text(json.dumps(info, indent=2))
            if warm is not None:
                warm_start.write_record(run_dir, warm)
        _truncate_metrics(run_dir / "metrics.jsonl", start)
        moved = environment_change(run_dir, resuming=ckpt is not None, packages=TRAIN_PACKAGES)
        if moved:  # a resumed run replays the uninterrupted one only on the machine it started on
            print(f"warning: {run_dir} started on another machine or packages ({moved}); it goes on, but will not "
                  "replay an uninterrupted run bit for bit", file=sys.stderr)

    batches.start, batches.stop = start, total if stop_at is None else min(total, stop_at)
    loader = DataLoader(ds, batch_sampler=batches, num_workers=cfg.num_workers, pin_memory=dev.type == "cuda",
                        collate_fn=default_collate)
    from tqdm import tqdm

    bar = tqdm(total=total, initial=start, disable=not progress or rank != 0, desc="train", unit="step")
    acc, n_acc, t_log, step = 0.0, 0, time.perf_counter(), start  # step: optimizer steps completed
    amp = cfg.amp and dev.type == "cuda"
    try:
        for k, batch in enumerate(loader, start):
            batch = to_device(batch, dev)
            if table is None:
                batch = finish_images(batch)
            else:
                batch["image_features"] = table[batch.pop("frames")]
            g = torch.Generator().manual_seed(step_seed(cfg.seed, k, rank, 1))
            noise = torch.randn(batch["action"].shape, generator=g).to(dev)
            t = torch.randint(0, cfg.num_train_timesteps, (noise.shape[0],), generator=g).to(dev)
            aux_noise = torch.randn(noise.shape[0], cfg.aux_dim, generator=g).to(dev) if cfg.aux_condition else None
            keep = None
            if cfg.image_cond_dropout > 0:
                keep = (torch.rand(noise.shape[0], generator=g) >= cfg.image_cond_dropout).float().to(dev)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp):
                loss = net(batch, noise, t, aux_noise, keep)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            sched.step()
            ema.update(model)
            step = done = k + 1
            acc, n_acc = acc + float(loss.detach()), n_acc + 1
            bar.update(1)
            if done % cfg.log_every == 0 or done == batches.stop:
                mean = _mean_over_ranks(acc / n_acc, dev, world)
                now = time.perf_counter()
                row = {"step": done, "loss": mean, "lr": sched.get_last_lr()[0], "steps_per_s": n_acc / (now - t_log),
                       "epoch": done / batches.per_epoch}
                if rank == 0:
                    with open(run_dir / "metrics.jsonl", "a") as f:
                        f.write(json.dumps(row) + "\n")
                bar.set_postfix(loss=f"{mean:.4f}", lr=f"{row['lr']:.2e}")
                acc, n_acc, t_log = 0.0, 0, now
            if validator is not None and (done % cfg.val_every == 0 or done == batches.stop):
                with open(run_dir / "metrics.jsonl", "a") as f:
                    f.write(json.dumps({"step": done, **validator(ema.model, dev)}) + "\n")
            if done % cfg.checkpoint_every == 0 and done != batches.stop and rank == 0:
                save_checkpoint(run_dir, done, total, model, ema, opt, sched, cfg)
    except KeyboardInterrupt:
        if rank == 0 and world == 1 and step > start:
            save_checkpoint(run_dir, step, total, model, ema, opt, sched, cfg)
        raise
    finally:
        bar.close()
    summary = {"run_dir": str(run_dir), "step": step, "total_steps": total, "world_size": world,
               "device": str(dev), "params": count_params(model), "finished": step >= total,
               "replica_max_diff": _replica_diff(model, dev, world)}
    if rank == 0:
        if step > start or latest_checkpoint(run_dir) is None:
            summary["checkpoint"] = str(save_checkpoint(run_dir, step, total, model, ema, opt, sched, cfg))
        rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines() if x.strip()] \
            if (run_dir / "metrics.jsonl").exists() else []
        losses = [r for r in rows if "loss" in r]
        summary["final_loss"] = losses[-1]["loss"] if losses else None
        checks = [r for r in rows if "val_loss" in r]
        if checks:
            summary["validation"] = checks[-1]
        summary["plot"] = str(plot_metrics(run_dir / "metrics.jsonl", run_dir / "metrics.png"))
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    if world > 1:
        dist.barrier()
    return summary


class _Loss(torch.nn.Module):
    """The policy's loss as a module's forward: DDP synchronizes gradients of what runs through forward."""

    def __init__(self, policy: DiffusionPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, batch, noise, t, aux_noise=None, image_keep=None):
        return self.policy.loss(batch, noise, t, aux_noise, image_keep)


def _mean_over_ranks(x: float, dev, world: int) -> float:
    if world == 1:
        return x
    t = torch.tensor([x], dtype=torch.float64, device=dev)
    dist.all_reduce(t)
    return float(t.item()) / world


def _replica_diff(model, dev, world: int) -> float:
    """Largest difference between ranks of any parameter's sum (0.0 when the replicas agree)."""
    if world == 1:
        return 0.0
    fp = torch.stack([p.detach().double().sum() for p in model.parameters()]).to(dev)
    hi, lo = fp.clone(), fp.clone()
    dist.all_reduce(hi, op=dist.ReduceOp.MAX)
    dist.all_reduce(lo, op=dist.ReduceOp.MIN)
    return float((hi - lo).abs().max().item())


def _truncate_metrics(path: Path, step: int) -> None:
    """On resume, drop log rows written after the checkpoint (they will be written again)."""
    if path.exists():
        keep = [x for x in path.read_text().splitlines() if x.strip() and json.loads(x)["step"] <= step]
        path.write_text("".join(x + "\n" for x in keep))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m policy.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="episode dataset directory")
    p.add_argument("run", help="run directory (resumed when it has checkpoints)")
    p.add_argument("--config", default="small", help="preset small|full or a TOML file")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--epochs", type=int, default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=JSON", help="override a config field")
    p.add_argument("--fresh", action="store_true", help="do not resume; start the run over")
    p.add_argument("--init-from", default=None, help="warm-start a new run from this run or bundle (policy.warm_start)")
    p.add_argument("--encoders-from", default=None, help="with --init-from: the image encoders and aux head of this "
                   "`sudd pretrain` run (policy.warm_start.load_pretrained_into)")
    p.add_argument("--stop-at", type=int, default=None, help="leave after this step with a checkpoint")
    p.add_argument("--device", default="auto")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    from policy.cli import parse_overrides

    overrides = parse_overrides(args.set)
    summary = train(args.data, args.config, args.run, steps=args.steps, epochs=args.epochs, resume=not args.fresh,
                    device=args.device, progress=not args.no_progress, overrides=overrides, init_from=args.init_from,
                    encoders_from=args.encoders_from, stop_at=args.stop_at)
    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary, indent=2))
    if dist.is_initialized():
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
