"""Scale-out episode generation: N worker processes (or Ray actors), each owning one shard writer.

Every episode is the pair (task, seed), seeds seed_offset..seed_offset+N-1 for each task, so a run is a set
of keys, and resuming is set difference: keys already committed in OUT are skipped. The parent hands out one
key at a time (episodes vary a lot in length), so a worker that dies loses at most its in-flight episode:
that key is logged and counted as an error, the worker is restarted on the same shard (which truncates the
half-written episode), and re-running the same command regenerates it. An exception in `episode_fn` is
logged with its key and counted, never fatal.

Local workers use the spawn start method: MuJoCo/EGL contexts do not survive fork. `episode_fn` must be
picklable (a module-level function). With Ray (`ray_address="auto"`, an address, or "local"), the same
`_Worker` runs as an actor per shard; OUT must then be on a filesystem every node shares.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
import sys
import time
import traceback
import zlib
from collections import deque
from collections.abc import Sequence
from multiprocessing.connection import wait
from pathlib import Path
from typing import Callable

import numpy as np

from datagen.schema import ACTION_DIM, EPISODE_META_KEYS, PROPRIO_DIM, EpisodeData
from datagen.store import Dataset, ShardWriter

log = logging.getLogger(__name__)
EpisodeFn = Callable[[str, int], EpisodeData]
MAX_RESTARTS_PER_WORKER = 3


class _Worker:
    """One shard writer plus the episode function: the unit both backends run."""

    def __init__(self, out: str, worker_id: str, episode_fn: EpisodeFn):
        self.writer = ShardWriter(out, worker_id)
        self.episode_fn = episode_fn

    def run(self, task: str, seed: int) -> dict:
        t0 = time.perf_counter()
        try:
            ep = self.episode_fn(task, seed)
            if (ep.meta.get("task"), ep.meta.get("seed")) != (task, seed):
                raise ValueError(f"episode_fn({task!r}, {seed}) returned an episode labelled "
                                 f"({ep.meta.get('task')!r}, {ep.meta.get('seed')!r})")
            self.writer.append(ep)
        except Exception as exc:
            where = traceback.extract_tb(exc.__traceback__)[-1]
            error = f"{type(exc).__name__}: {exc} (at {Path(where.filename).name}:{where.lineno} in {where.name})"
            return {"task": task, "seed": seed, "ok": False, "error": error, "seconds": time.perf_counter() - t0}
        return {"task": task, "seed": seed, "ok": True, "success": bool(ep.meta.get("success")),
                "steps": len(ep), "seconds": time.perf_counter() - t0}

    def close(self) -> None:
        self.writer.close()


def _process_main(out: str, worker_id: str, episode_fn: EpisodeFn, conn) -> None:
    """Child process: announce readiness, then run keys sent by the parent until it sends None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    try:
        worker = _Worker(out, worker_id, episode_fn)
    except Exception as exc:
        conn.send({"fatal": f"worker {worker_id} could not start: {type(exc).__name__}: {exc}"})
        return
    try:
        conn.send({"ready": worker_id})
        while (key := conn.recv()) is not None:
            conn.send(worker.run(*key))
    finally:
        worker.close()


def episode_keys(tasks: list[str], episodes_per_task: int, seed_offset: int = 0,
                 seeds: Sequence[int] | None = None) -> list[tuple[str, int]]:
    """(task, seed) for every task: the given seeds, else seed_offset .. seed_offset + episodes_per_task - 1."""
    seeds = range(seed_offset, seed_offset + episodes_per_task) if seeds is None else seeds
    return [(t, int(s)) for t in tasks for s in seeds]


def generate(tasks: list[str], episodes_per_task: int, out: Path, workers: int, episode_fn: EpisodeFn,
             seed_offset: int = 0, ray_address: str | None = None, progress: bool = True,
             seeds: Sequence[int] | None = None) -> dict:
    """Generate every missing (task, seed) episode into OUT; returns a summary of this run.

    `seeds`, when given, are the seeds for every task instead of seed_offset's range (episodes_per_task unused).

    Summary: requested, skipped (already in OUT), episodes (committed by this run), successes (of those,
    meta["success"] true), errors (exceptions or dead workers: not committed, retried by the next run),
    error_keys, per_task counts, wall_s, episodes_per_hour, total (committed in OUT afterwards).
    """
    if not tasks or episodes_per_task < 0 or workers < 1:
        raise ValueError(f"need tasks, episodes_per_task >= 0 and workers >= 1; got {tasks!r}, "
                         f"{episodes_per_task}, {workers}")
    out = Path(out)
    keys = episode_keys(list(tasks), episodes_per_task, seed_offset, seeds)
    done, bad_shards = set(), set()
    if (out / "shards").is_dir():
        ds = Dataset(out)
        done, bad_shards = ds.completed_keys(), set(ds.skipped)
    todo = [k for k in keys if k not in done]
    ids = [f"w{k:03d}" for k in range(workers + len(bad_shards)) if f"w{k:03d}" not in bad_shards]
    ids = ids[:max(1, min(workers, len(todo)))]
    stats = _Stats(keys, len(keys) - len(todo), len(todo), progress)
    try:
        if todo and ray_address:
            _run_ray(out, ids, episode_fn, todo, stats, ray_address)
        elif todo:
            _run_processes(out, ids, episode_fn, todo, stats)
    finally:
        stats.bar.close()
    return stats.summary(backend="ray" if ray_address else "process", workers=len(ids), out=str(out))


class _Stats:
    """Counts results, drives the progress bar, builds the summary."""

    def __init__(self, keys, skipped: int, todo: int, progress: bool):
        from tqdm import tqdm

        self.t0 = time.perf_counter()
        self.requested, self.skipped = len(keys), skipped
        self.per_task = {t: {"episodes": 0, "successes": 0, "errors": 0} for t, _ in keys}
        self.episodes = self.successes = 0
        self.error_keys: list[dict] = []
        self.bar = tqdm(total=todo, desc=f"datagen ({skipped} done before)", unit="ep", file=sys.stderr,
                        disable=not progress, dynamic_ncols=True)

    def add(self, r: dict) -> None:
        row = self.per_task[r["task"]]
        if r["ok"]:
            self.episodes += 1
            row["episodes"] += 1
            self.successes += r["success"]
            row["successes"] += r["success"]
        else:
            row["errors"] += 1
            self.error_keys.append({"task": r["task"], "seed": r["seed"], "error": r["error"]})
            log.warning("episode (%s, %d) failed: %s", r["task"], r["seed"], r["error"])
        self.bar.set_postfix({"success": self.successes, "fail": self.episodes - self.successes,
                              "error": len(self.error_keys)}, refresh=False)
        self.bar.update(1)

    def summary(self, **extra) -> dict:
        self.bar.close()
        wall = time.perf_counter() - self.t0
        return dict(requested=self.requested, skipped=self.skipped, episodes=self.episodes,
                    successes=self.successes, errors=len(self.error_keys), error_keys=self.error_keys,
                    per_task=self.per_task, total=self.skipped + self.episodes, wall_s=round(wall, 3),
                    episodes_per_hour=round(self.episodes * 3600.0 / wall, 1) if wall > 0 else 0.0, **extra)


def _run_processes(out: Path, ids: list[str], episode_fn: EpisodeFn, todo: list, stats: _Stats) -> None:
    ctx = mp.get_context("spawn")
    pending = deque(todo)
    procs: dict[str, tuple] = {}  # worker id -> (process, parent end of its pipe)
    inflight: dict[str, tuple | None] = {}
    restarts = {wid: 0 for wid in ids}

    def start(wid: str) -> None:
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_process_main, args=(str(out), wid, episode_fn, child), name=f"datagen-{wid}",
                        daemon=True)
        p.start()
        child.close()
        procs[wid], inflight[wid] = (p, parent), None

    def dispatch(wid: str) -> None:
        inflight[wid] = pending.popleft() if pending else None
        procs[wid][1].send(inflight[wid])

    try:
        for wid in ids:
            start(wid)
        while procs:
            for conn in wait([c for _, c in procs.values()]):
                wid = next(w for w, (_, c) in procs.items() if c is conn)
                try:
                    msg = conn.recv()
                except (EOFError, OSError):  # the worker died
                    proc = procs.pop(wid)[0]
                    proc.join()
                    key = inflight.pop(wid)
                    if key is not None:
                        stats.add({"task": key[0], "seed": key[1], "ok": False,
                                   "error": f"worker {wid} died (exit code {proc.exitcode}) while running it"})
                    if pending and restarts[wid] < MAX_RESTARTS_PER_WORKER:
                        restarts[wid] += 1
                        log.warning("worker %s died (exit code %s); restarting it", wid, proc.exitcode)
                        start(wid)
                    continue
                if "fatal" in msg:
                    raise RuntimeError(msg["fatal"])
                if "ready" not in msg:
                    stats.add(msg)
                dispatch(wid)
                if inflight[wid] is None:  # it was sent the stop signal
                    procs.pop(wid)[0].join(timeout=30)
        if pending:
            raise RuntimeError(f"all workers died; {len(pending)} episodes not attempted (re-run to resume)")
    except BaseException:
        for proc, _ in procs.values():
            proc.terminate()
        if isinstance(sys.exc_info()[1], KeyboardInterrupt):
            log.warning("interrupted: committed episodes are kept; re-run the same command to resume")
        raise
    finally:
        for proc, conn in procs.values():
            proc.join(timeout=10)
            conn.close()


def _run_ray(out: Path, ids: list[str], episode_fn: EpisodeFn, todo: list, stats: _Stats, address: str) -> None:
    import ray

    if not ray.is_initialized():
        ray.init(address=None if address == "local" else address, include_dashboard=False)
    actor_cls = ray.remote(num_cpus=1)(_Worker)
    pending = deque(todo)
    actors = {wid: actor_cls.remote(str(out.resolve()), wid, episode_fn) for wid in ids}
    running: dict = {}  # object ref -> (worker id, key)
    restarts = {wid: 0 for wid in ids}

    def dispatch(wid: str) -> None:
        if pending:
            key = pending.popleft()
            running[actors[wid].run.remote(*key)] = (wid, key)

    try:
        for wid in ids:
            dispatch(wid)
        while running:
            [ref], _ = ray.wait(list(running), num_returns=1)
            wid, key = running.pop(ref)
            try:
                stats.add(ray.get(ref))
            except ray.exceptions.RayActorError as exc:
                stats.add({"task": key[0], "seed": key[1], "ok": False, "error": f"actor {wid} died: {exc}"})
                if restarts[wid] >= MAX_RESTARTS_PER_WORKER:
                    continue
                restarts[wid] += 1
                actors[wid] = actor_cls.remote(str(out.resolve()), wid, episode_fn)
            dispatch(wid)
        if pending:
            raise RuntimeError(f"all Ray actors died; {len(pending)} episodes not attempted (re-run to resume)")
    finally:
        for actor in actors.values():
            try:
                ray.get(actor.close.remote(), timeout=30)
            except Exception:  # a dead actor has nothing to close
                pass
            ray.kill(actor)


def synthetic_episode(task: str, seed: int, steps: int | None = None, size: int = 32) -> EpisodeData:
    """A small, valid, deterministic EpisodeData without the simulator: a coloured square moving over a
    gradient in both cameras. For tests and for measuring the store and the scale-out on their own."""
    rng = np.random.default_rng([zlib.crc32(task.encode()), seed])
    T = steps or int(rng.integers(12, 30))
    yy, xx = np.mgrid[0:size, 0:size]
    base = np.stack([xx * 255 // size, yy * 255 // size, np.full_like(xx, 60)], -1).astype(np.uint8)
    images = {}
    for cam, color in (("scene", (220, 40, 40)), ("wrist", (40, 200, 60))):
        frames = np.repeat(base[None], T, 0)
        for t in range(T):
            x = int((size - 8) * t / max(1, T - 1))
            frames[t, size // 3:size // 3 + 8, x:x + 8] = color
        images[cam] = frames
    n_sub = 2
    meta = {k: None for k in EPISODE_META_KEYS}
    meta.update(task=task, seed=int(seed), instruction=f"do {task}", subtasks=[f"{task} part {i + 1}"
                for i in range(n_sub)], success=bool(rng.random() < 0.7), check_success=bool(rng.random() < 0.7),
                label={"success": None, "source": "synthetic"}, retries=int(rng.integers(0, 3)),
                planner="offline", dr={"preset": "off"})
    meta["label"]["success"] = meta["success"]
    return EpisodeData(images=images, proprio=rng.normal(size=(T, PROPRIO_DIM)).astype(np.float32),
                       action=rng.normal(size=(T, ACTION_DIM)).astype(np.float32),
                       subtask=(np.arange(T) * n_sub // T).astype(np.int16), time=np.arange(T) / 10.0, meta=meta)
