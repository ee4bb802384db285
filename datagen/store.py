"""The episode dataset on disk: zarr v3 shards, one per writer, append-only and crash-safe.

Layout (the documented schema; `SCHEMA_VERSION` in datagen.schema versions it)::

    DIR/shards/<worker-id>.zarr          one zarr v3 group per writer (a merged store is DIR/shards/merged.zarr)
      zarr.json  attrs: {"format": "sudd-episodes", "schema_version": int, "worker": str}
      data/scene_rgb  (N, H, W, 3) uint8    chunks (8, H, W, 3)   blosc zstd-3, then crc32c
      data/wrist_rgb  (N, H, W, 3) uint8    chunks (8, H, W, 3)   blosc zstd-3, then crc32c
      data/proprio    (N, 16) float32       chunks (4096, 16)     blosc zstd-5 + byte shuffle, then crc32c
      data/action     (N, 10) float32       chunks (4096, 10)
      data/subtask    (N,) int16            chunks (4096,)
      data/time       (N,) float64          chunks (4096,)
      meta/episodes      (E,) string        one JSON object per episode: EpisodeData.meta plus
                                            "_schema_version", "_length" and "_sha256" (content hash)
      meta/episode_ends  (E,) int64         cumulative step counts; episode e = steps [ends[e-1], ends[e])

Step arrays are the episodes concatenated. Image chunks of 8 steps keep a training read of a short window
cheap (one or two ~0.4 MB chunks per camera at 128x128); low-dimensional arrays are tiny, so big chunks.
Every chunk carries a crc32c checksum: blosc alone decodes a truncated chunk into garbage without an error.

Crash safety: an append writes the step arrays, then the episode's JSON, then `episode_ends` LAST - that
entry is the commit point. zarr's LocalStore replaces every file atomically (temp file + rename), so a killed
process leaves either the old or the new version of each chunk, never a torn one. Readers see only committed
episodes; a writer reopening a shard truncates the uncommitted tail (the episode is regenerated on resume).
Not fsync'd: a power cut may lose recent episodes but not corrupt older ones' files on journaling filesystems.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import re
import warnings
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec, ZstdCodec

from datagen.schema import CAMERAS, SCHEMA_VERSION, EpisodeData

FORMAT = "sudd-episodes"
IMAGE_CHUNK_STEPS = 8
LOWDIM_CHUNK_STEPS = 4096
META_CHUNK = 64  # episodes per chunk of meta/episodes (each append rewrites one chunk of JSON)
ENDS_CHUNK = 1024
STEP_ARRAYS = {  # name -> (dtype, chunk steps, codec)
    "scene_rgb": ("uint8", IMAGE_CHUNK_STEPS, "img"), "wrist_rgb": ("uint8", IMAGE_CHUNK_STEPS, "img"),
    "proprio": ("float32", LOWDIM_CHUNK_STEPS, "low"), "action": ("float32", LOWDIM_CHUNK_STEPS, "low"),
    "subtask": ("int16", LOWDIM_CHUNK_STEPS, "low"), "time": ("float64", LOWDIM_CHUNK_STEPS, "low"),
}
_CODECS = {"img": (BloscCodec(cname="zstd", clevel=3, shuffle="noshuffle"), Crc32cCodec()),
           "low": (BloscCodec(cname="zstd", clevel=5, shuffle="shuffle"), Crc32cCodec()),
           "meta": (ZstdCodec(level=3), Crc32cCodec())}
_WORKER_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
log = logging.getLogger(__name__)


class StoreError(RuntimeError):
    """A shard that cannot be read or written as asked; the message names the shard."""


class SchemaVersionError(StoreError):
    """A shard written with another SCHEMA_VERSION: refused, never mixed in."""


def shard_dir(root: str | Path) -> Path:
    return Path(root) / "shards"


def step_arrays(ep: EpisodeData) -> dict[str, np.ndarray]:
    """The episode's per-step arrays under their on-disk names and dtypes."""
    missing = [c for c in CAMERAS if c not in ep.images]
    if missing:
        raise ValueError(f"episode has no images from camera(s) {missing}; the store records {list(CAMERAS)}")
    out = {f"{c}_rgb": ep.images[c] for c in CAMERAS}
    out.update(proprio=ep.proprio, action=ep.action, subtask=ep.subtask, time=ep.time)
    return {k: np.ascontiguousarray(v, dtype=STEP_ARRAYS[k][0]) for k, v in out.items()}


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"episode meta value {x!r} ({type(x).__name__}) is not JSON-serializable")


def canonical_meta(meta: dict) -> str:
    """The JSON text the store keeps for `meta` (sorted keys, numpy converted): what the hash covers."""
    return json.dumps(json.loads(json.dumps(meta, default=_jsonable)), sort_keys=True, separators=(",", ":"))


def episode_hash(arrays: dict[str, np.ndarray], meta: dict) -> str:
    """sha256 of the decoded content (dtype, shape, bytes of each array, then the canonical meta)."""
    h = hashlib.sha256()
    for name in STEP_ARRAYS:
        a = arrays[name]
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(canonical_meta({k: v for k, v in meta.items() if not k.startswith("_")}).encode())
    return h.hexdigest()


def episode_key(meta: dict) -> tuple:
    """(task, seed) names an episode in a store; a phase cut (policy.phase_data) keeps its source's seed, and maybe
    its family, so its key adds the phase."""
    cut = meta.get("phase_of")
    return (meta["task"], int(meta["seed"])) + (() if cut is None else (int(cut["phase"]),))


def committed(group: zarr.Group, name: str) -> tuple[np.ndarray, list[dict]]:
    """The committed episodes of a shard group: (episode_ends, parsed metas). Raises StoreError if corrupt.

    Tolerates exactly the states an interrupted append can leave: step arrays longer than the last end, one
    extra JSON entry, or one trailing `episode_ends` entry still at its fill value (-1).
    """
    if "meta/episode_ends" not in group and "data" not in group:  # killed while the shard was being created
        return np.zeros(0, np.int64), []
    try:
        ends = np.asarray(group["meta/episode_ends"][:], dtype=np.int64)
        texts = list(group["meta/episodes"][:])
        if len(ends) and ends[-1] == -1:
            ends = ends[:-1]
        if len(texts) not in (len(ends), len(ends) + 1):
            raise StoreError(f"{len(ends)} episode ends but {len(texts)} metadata entries")
        if len(ends) and (ends[0] <= 0 or np.any(np.diff(ends) <= 0)):
            raise StoreError(f"episode_ends is not strictly increasing: {ends[:8].tolist()}...")
        for key in STEP_ARRAYS if len(ends) else ():
            if f"data/{key}" not in group or group[f"data/{key}"].shape[0] < ends[-1]:
                raise StoreError(f"data/{key} is missing or shorter than the committed {ends[-1]} steps")
        metas = [json.loads(t) for t in texts[:len(ends)]]
    except StoreError as exc:
        raise StoreError(f"shard {name}: {exc}") from None
    except Exception as exc:  # zarr/numcodecs/json errors on garbage files
        raise StoreError(f"shard {name}: unreadable metadata ({type(exc).__name__}: {exc})") from exc
    for i, (m, n) in enumerate(zip(metas, np.diff(ends, prepend=0))):
        if not isinstance(m, dict) or m.get("_length") != int(n) or "_sha256" not in m:
            raise StoreError(f"shard {name}: episode {i} metadata does not match its {n} steps")
    return ends, metas


def open_shard(path: Path, mode: str = "r") -> zarr.Group:
    """Open a shard group, refusing other formats and other schema versions."""
    name = path.stem
    try:
        group = zarr.open_group(path, mode=mode)
        attrs = dict(group.attrs)
    except Exception as exc:
        raise StoreError(f"shard {name} ({path}) is not a readable zarr group: {type(exc).__name__}: {exc}") from exc
    if attrs.get("format") != FORMAT:
        raise StoreError(f"shard {name} ({path}) is not a sudd episode shard (format={attrs.get('format')!r})")
    if attrs.get("schema_version") != SCHEMA_VERSION:
        raise SchemaVersionError(
            f"shard {name} ({path}) was written with episode schema version {attrs.get('schema_version')}, this "
            f"code reads version {SCHEMA_VERSION}; regenerate it, or read it with the matching sudd version")
    return group


class ShardWriter:
    """Appends episodes to DIR/shards/<worker_id>.zarr; one writer per shard (an flock guards it).

    Opening repairs the shard: whatever an interrupted append left past the last commit is truncated.
    """

    def __init__(self, root: str | Path, worker_id: str):
        if not _WORKER_ID.match(worker_id):
            raise ValueError(f"worker id {worker_id!r} must be 1-64 letters, digits, '_', '.', '-'")
        self.name = worker_id
        self.path = shard_dir(root) / f"{worker_id}.zarr"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = open(self.path.parent / f"{worker_id}.lock", "w")
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock.close()
            raise StoreError(f"shard {worker_id} in {root} is being written by another process") from None
        try:
            self._open(worker_id)
        except BaseException:
            self.close()
            raise

    def _open(self, worker_id: str) -> None:
        if not (self.path / "zarr.json").exists():
            zarr.open_group(self.path, mode="w",
                            attributes={"format": FORMAT, "schema_version": SCHEMA_VERSION, "worker": worker_id})
        self.group = g = open_shard(self.path, mode="a")
        if "meta/episodes" not in g:
            g.create_array("meta/episodes", shape=(0,), chunks=(META_CHUNK,), dtype=str, compressors=_CODECS["meta"])
        if "meta/episode_ends" not in g:
            g.create_array("meta/episode_ends", shape=(0,), chunks=(ENDS_CHUNK,), dtype="int64", fill_value=-1,
                           compressors=_CODECS["meta"])
        for tmp in self.path.rglob("*.partial"):  # temp files of writes killed before their rename
            tmp.unlink(missing_ok=True)
        self._repair()

    def _repair(self) -> None:
        g = self.group
        ends, metas = committed(g, self.name)
        has_data = "data" in g and all(k in g["data"] for k in STEP_ARRAYS)
        self.steps = int(ends[-1]) if len(ends) else 0
        self.keys = {episode_key(m) for m in metas}
        g["meta/episodes"].resize((len(ends),))
        g["meta/episode_ends"].resize((len(ends),))
        if has_data:
            for key in STEP_ARRAYS:
                arr = g[f"data/{key}"]
                if arr.shape[0] > self.steps:
                    log.warning("shard %s: dropping %d uncommitted steps of an interrupted episode",
                                self.name, arr.shape[0] - self.steps)
                    arr.resize((self.steps,) + arr.shape[1:])
        elif "data" in g:
            del g["data"]  # a first append that never committed

    def append(self, ep: EpisodeData) -> int:
        """Write one episode and commit it; returns its index in this shard."""
        ep.validate()
        arrays = step_arrays(ep)
        key = episode_key(ep.meta)
        if key in self.keys:
            raise StoreError(f"shard {self.name} already holds episode {key}")
        T = len(ep)
        if T < 1:
            raise ValueError("an episode needs at least one step")
        data = self._data_arrays(arrays)
        start, stop = self.steps, self.steps + T
        for name, arr in arrays.items():
            data[name].resize((stop,) + arr.shape[1:])
            data[name][start:stop] = arr
        record = json.loads(canonical_meta(ep.meta))
        record.update(_schema_version=SCHEMA_VERSION, _length=T, _sha256=episode_hash(arrays, ep.meta))
        index = len(self.keys)
        eps = self.group["meta/episodes"]
        eps.resize((index + 1,))
        eps[index] = json.dumps(record, sort_keys=True)
        self._commit(index, stop)
        self.steps = stop
        self.keys.add(key)
        return index

    def _commit(self, index: int, stop: int) -> None:
        ends = self.group["meta/episode_ends"]
        ends.resize((index + 1,))
        ends[index] = stop

    def _data_arrays(self, arrays: dict[str, np.ndarray]) -> dict:
        g = self.group
        out = {}
        for name, arr in arrays.items():
            dtype, chunk, codec = STEP_ARRAYS[name]
            path = f"data/{name}"
            if path not in g:
                g.create_array(path, shape=(0,) + arr.shape[1:], chunks=(chunk,) + arr.shape[1:], dtype=dtype,
                               compressors=_CODECS[codec], fill_value=0)
            out[name] = g[path]
            if out[name].shape[1:] != arr.shape[1:]:
                raise StoreError(f"shard {self.name}: {name} has per-step shape {out[name].shape[1:]}, "
                                 f"this episode has {arr.shape[1:]} (one image size per shard)")
        return out

    def close(self) -> None:
        if not self._lock.closed:
            fcntl.flock(self._lock, fcntl.LOCK_UN)
            self._lock.close()

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Dataset:
    """Read-only view of every shard under DIR (worker shards or a merged store: same layout).

    A shard that cannot be read is named in a RuntimeWarning and skipped (`skipped` maps name -> reason);
    a shard of another schema version raises SchemaVersionError. `verify=True` also decodes every episode
    and checks its content hash, skipping shards with corrupt chunks. Episodes are indexed 0..len-1 in
    (shard name, position) order.
    """

    def __init__(self, root: str | Path, verify: bool = False):
        self.root = Path(root)
        if not shard_dir(self.root).is_dir():
            raise StoreError(f"{self.root} is not a sudd dataset (no shards/ folder)")
        self.shards: dict[str, tuple[zarr.Group, np.ndarray, list[dict]]] = {}
        self.skipped: dict[str, str] = {}
        for path in sorted(shard_dir(self.root).glob("*.zarr")):
            try:
                group = open_shard(path)
                ends, metas = committed(group, path.stem)
                self.shards[path.stem] = (group, ends, metas)
                if verify:
                    self._verify(path.stem)
            except SchemaVersionError:
                raise
            except StoreError as exc:
                self.shards.pop(path.stem, None)
                self.skipped[path.stem] = str(exc)
                warnings.warn(f"skipping {exc}", RuntimeWarning, stacklevel=2)
        self._index = [(name, i) for name, (_, _, metas) in self.shards.items() for i in range(len(metas))]
        seen: dict[tuple, str] = {}
        for name, i in self._index:
            key = episode_key(self.shards[name][2][i])
            if key in seen:
                warnings.warn(f"episode {key} is in both shard {seen[key]} and shard {name}", RuntimeWarning)
            seen.setdefault(key, name)

    def __len__(self) -> int:
        return len(self._index)

    @property
    def num_steps(self) -> int:
        return sum(int(ends[-1]) for _, ends, _ in self.shards.values() if len(ends))

    def _locate(self, i: int) -> tuple[str, zarr.Group, int, int, dict]:
        name, j = self._index[i]
        group, ends, metas = self.shards[name]
        return name, group, int(ends[j - 1]) if j else 0, int(ends[j]), metas[j]

    def meta(self, i: int) -> dict:
        """Episode i's metadata as recorded (with the store's "_" keys)."""
        return self._locate(i)[4]

    def episodes(self) -> list[dict]:
        """One row per episode: index, shard, length, and its metadata (task, seed, success, ...)."""
        return [dict({k: v for k, v in self.meta(i).items() if not k.startswith("_")},
                     index=i, shard=self._index[i][0], length=self.meta(i)["_length"]) for i in range(len(self))]

    def window(self, i: int, start: int = 0, stop: int | None = None, fields=tuple(STEP_ARRAYS)) -> dict:
        """Steps [start, stop) of episode i (clipped to the episode) for the named on-disk arrays.

        Reads only the chunks the window touches: the access pattern of a sequence-sampling trainer.
        """
        name, group, s0, s1, _ = self._locate(i)
        a, b = s0 + max(0, start), s1 if stop is None else min(s1, s0 + stop)
        try:
            return {f: group[f"data/{f}"][a:b] for f in fields}
        except Exception as exc:
            raise StoreError(f"shard {name}: episode {i} is unreadable ({type(exc).__name__}: {exc})") from exc

    def episode(self, i: int) -> EpisodeData:
        arrays = self.window(i)
        meta = {k: v for k, v in self.meta(i).items() if not k.startswith("_")}
        return EpisodeData(images={c: arrays[f"{c}_rgb"] for c in CAMERAS}, proprio=arrays["proprio"],
                           action=arrays["action"], subtask=arrays["subtask"], time=arrays["time"], meta=meta)

    def iter_steps(self, fields=tuple(STEP_ARRAYS)):
        """Yield one dict per step: episode index, step index and the named arrays' values at that step."""
        for i in range(len(self)):
            arrays = self.window(i, fields=fields)
            for t in range(self.meta(i)["_length"]):
                yield dict({f: arrays[f][t] for f in fields}, episode=i, step=t)

    def completed_keys(self) -> set[tuple]:
        """The episode keys (`episode_key`) committed so far: a resumed generation run skips these."""
        return {episode_key(self.meta(i)) for i in range(len(self))}

    def _verify(self, name: str) -> None:
        group, ends, metas = self.shards[name]
        for j, m in enumerate(metas):
            a, b = (int(ends[j - 1]) if j else 0), int(ends[j])
            try:
                arrays = {f: group[f"data/{f}"][a:b] for f in STEP_ARRAYS}
            except Exception as exc:
                raise StoreError(f"shard {name}: episode {j} is unreadable ({type(exc).__name__})") from exc
            if episode_hash(arrays, m) != m["_sha256"]:
                raise StoreError(f"shard {name}: episode {j} does not match its content hash")

    def content_hash(self, verify: bool = False) -> str:
        """sha256 over the set of (task, seed, episode content hash): independent of sharding and order,
        so a merged store hashes like its sources. verify=True recomputes each episode's hash from data."""
        if verify:
            for name in self.shards:
                self._verify(name)
        lines = sorted({f"{m['task']}\t{int(m['seed'])}\t{m['_sha256']}\n" for _, _, ms in self.shards.values()
                        for m in ms})
        return hashlib.sha256((f"sudd-dataset/{SCHEMA_VERSION}\n" + "".join(lines)).encode()).hexdigest()

    def merge(self, out_dir: str | Path, shard: str = "merged", progress=None, tasks=None) -> Path:
        """Copy every episode (of `tasks`, if given) into one shard OUT/shards/<shard>.zarr (readable with Dataset).

        Duplicated episode keys (`episode_key`) are written once; re-running an interrupted merge continues it.
        `progress`, if given, is called once per episode of this dataset (copied, already there or left out).
        """
        out_dir = Path(out_dir)
        if out_dir.resolve() == self.root.resolve():
            raise StoreError("merge into a new directory, not into the dataset being read")
        with ShardWriter(out_dir, shard) as writer:
            for i in range(len(self)):
                m = self.meta(i)
                if (tasks is None or m["task"] in tasks) and episode_key(m) not in writer.keys:
                    writer.append(self.episode(i))
                if progress is not None:
                    progress()
        return out_dir
