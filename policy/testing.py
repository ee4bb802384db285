"""Small fixtures for tests and smoke runs: a synthetic episode dataset, a tiny config, a hash embedder, a tiny
run, a cheap copy of a bundle to break.

Kept in the package (like datagen.workers.synthetic_episode) so tests, benchmarks and a quick manual
`sudd train` on fake data all build the same things.
"""

from __future__ import annotations

import shutil
import zlib
from pathlib import Path

import numpy as np

from datagen.store import ShardWriter
from datagen.workers import synthetic_episode

# A policy that trains in seconds on 32x32 synthetic episodes (tests only: far too small to learn a task).
TINY = {"image_size": [32, 32], "crop_size": [28, 28], "encoder_widths": [8, 16], "encoder_blocks": [1, 1],
        "keypoints": 8, "image_feature_dim": 16, "proprio_feature_dim": 16, "text_feature_dim": 16,
        "down_dims": [16, 32], "step_embed_dim": 16, "batch_size": 8, "warmup_steps": 2, "lr": 1e-3,
        "checkpoint_every": 4, "log_every": 2}


def synthetic_dataset(root: str | Path, episodes: int = 6, tasks: tuple[str, ...] = ("pick_place",),
                      size: int = 32, steps: int | None = None, smooth: bool = False,
                      instructions: dict[str, str] | None = None) -> Path:
    """Write `episodes` synthetic episodes per task (about 70 % labelled successful) to root/shards/w0.zarr.

    smooth=True replaces the i.i.d. random proprio/actions of `synthetic_episode` by a trajectory that
    follows the square moving across the images (a straight reach, a constant orientation, the gripper
    closing halfway), so a policy has something learnable: the loss of a few training steps must drop.
    instructions: task -> the command its episodes record (default "do TASK").
    """
    with ShardWriter(root, "w0") as w:
        for task in tasks:
            for seed in range(episodes):
                ep = synthetic_episode(task, seed, steps=steps, size=size)
                if smooth:
                    smooth_episode(ep, seed)
                if instructions and task in instructions:
                    ep.meta["instruction"] = instructions[task]
                w.append(ep)
    return Path(root)


def smooth_episode(ep, seed: int) -> None:
    T = len(ep)
    s = np.linspace(0.0, 1.0, T)[:, None]
    start = np.array([0.3 + 0.02 * (seed % 5), -0.2, 0.25])
    pos = start + s * np.array([0.0, 0.4, -0.1])
    rot = np.tile([1.0, 0, 0, 0, -1.0, 0], (T, 1))
    grip = (s > 0.5).astype(float)
    q = np.hstack([s * k for k in (0.5, -0.3, 0.2, 0.1, -0.4, 0.3)])
    ep.proprio = np.hstack([pos, rot, grip, q]).astype(np.float32)
    nxt = np.vstack([pos[1:], pos[-1:]])
    ep.action = np.hstack([nxt, rot, np.vstack([grip[1:], grip[-1:]])]).astype(np.float32)


def hash_embedder(texts: list[str]) -> np.ndarray:
    """A deterministic stand-in for MiniLM: one random unit vector per distinct string (no model load)."""
    out = np.stack([np.random.default_rng(zlib.crc32(t.encode())).normal(size=384) for t in texts]) if texts \
        else np.zeros((0, 384))
    return (out / np.linalg.norm(out, axis=-1, keepdims=True).clip(1e-12)).astype(np.float32)


def tiny_run(root: str | Path) -> Path:
    """A TINY run of 6 steps on 6 smooth synthetic episodes of two families (ROOT/data, ROOT/run): something
    to export and load in a few seconds."""
    from policy.train import train

    root = Path(root)
    data = synthetic_dataset(root / "data", episodes=6, tasks=("pick_place", "stack"), smooth=True)
    train(data, dict(TINY), root / "run", steps=6, embedder=hash_embedder, progress=False, threads=1)
    return root / "run"


STACK = "stack the red block on the blue block"
# The shipped bundle's kind of policy (tcp frames, the head's points conditioning the denoiser, flow matching).
SHIPPED_LIKE = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "aux_condition": True,
                "aux_release_frame": "base", "objective": "flow", "obs_horizon": 1, "text_goal": True}


def goal_query_run(root: str | Path) -> tuple[Path, Path]:
    """(ROOT/data, ROOT/run): a TINY SHIPPED_LIKE run of 4 steps on pick_place and stack episodes whose stack
    command (STACK) names two blocks, for the goal query and its locator."""
    from policy.train import train

    root = Path(root)
    data = synthetic_dataset(root / "data", episodes=6, tasks=("pick_place", "stack"), smooth=True,
                             instructions={"stack": STACK, "pick_place": "put the red cube in the blue bin"})
    train(data, dict(TINY), root / "run", steps=4, embedder=hash_embedder, progress=False, threads=1,
          overrides=SHIPPED_LIKE)
    return data, root / "run"


def random_observation(bundle, seed: int = 0) -> tuple[dict, np.ndarray]:
    """Random uint8 frames per camera and a proprio inside the bundle's stats range, as Bundle.act takes them."""
    rng = np.random.default_rng(seed)
    images = {c: rng.integers(0, 256, (bundle.obs_horizon, *bundle.image_size, 3), dtype=np.uint8)
              for c in bundle.cameras}
    lo, hi = bundle.stats["proprio_min"], bundle.stats["proprio_max"]
    return images, (lo + (hi - lo) * rng.random((bundle.obs_horizon, bundle.proprio_dim))).astype(np.float32)


def linked_copy(bundle_dir: str | Path, dst: str | Path) -> Path:
    """A bundle's copy whose large files are symlinks (fast); manifest and stats are real files to edit."""
    dst = Path(dst)
    dst.mkdir()
    for p in Path(bundle_dir).iterdir():
        if p.name in ("manifest.json", "stats.npz"):
            shutil.copyfile(p, dst / p.name)
        else:
            (dst / p.name).symlink_to(p.resolve())  # a relative source would dangle from dst
    return dst


def constant_turn_locator(bundle_dir: str | Path, dst: str | Path, family: str, turn_deg: float,
                          period_deg: float = 90.0) -> Path:
    """A linked copy of a bundle with a turn query for `family` whose turn locator answers every frame with the
    same sure turn, `turn_deg` from the wrist's yaw (its graph built by hand: a constant tiled over the batch), to
    test what the runtime does with an answer it can predict."""
    import json

    import onnx
    from onnx import TensorProto, helper

    from policy.bundle import sha256_file
    from policy.grasp_axis import turn_label

    out = linked_copy(bundle_dir, dst)
    m = json.loads((out / "manifest.json").read_text())
    feeds = [i for i in m["graphs"]["obs_encoder"]["inputs"] if i["name"].startswith("image_")
             or i["name"] == "text_embedding"]
    row = np.zeros((1, 8), np.float32)
    row[0, 6:8] = turn_label(np.radians(turn_deg), 0.0, np.radians(period_deg))
    kinds = {"uint8": TensorProto.UINT8, "float32": TensorProto.FLOAT}
    nodes = [helper.make_node("Shape", ["text_embedding"], ["shape"], start=0, end=1),
             helper.make_node("Concat", ["shape", "one"], ["reps"], axis=0),
             helper.make_node("Tile", ["answer", "reps"], ["aux_points"])]
    graph = helper.make_graph(
        nodes, "constant_turn", [helper.make_tensor_value_info(i["name"], kinds[i["dtype"]], i["shape"])
                                 for i in feeds],
        [helper.make_tensor_value_info("aux_points", TensorProto.FLOAT, ["B", 8])],
        [onnx.numpy_helper.from_array(row, "answer"), onnx.numpy_helper.from_array(np.array([1], np.int64), "one")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", m["opset"])])
    (out / "turn_locator.onnx").unlink(missing_ok=True)  # a link to the source bundle's own: never write through it
    onnx.save(model, out / "turn_locator.onnx")
    m["graphs"]["turn_locator"] = {"file": "turn_locator.onnx", "inputs": feeds,
                                   "outputs": [{"name": "aux_points", "shape": ["B", 8], "dtype": "float32"}]}
    m["files"]["turn_locator.onnx"] = {"bytes": (out / "turn_locator.onnx").stat().st_size,
                                       "sha256": sha256_file(out / "turn_locator.onnx")}
    m["turn_query"] = {"families": [family], "period_deg": period_deg}
    (out / "manifest.json").write_text(json.dumps(m, indent=2))
    return out


class StillBundle:
    """A bundle stand-in for run_policy_episode with a goal query (`look`: asked from that look pose,
    runtime/look.py; with `turn_deg` a turn query too, answering the turn from the wrist's yaw now to the first
    asked yaw plus `turn_deg`, for a square footprint, a sure answer of length `turn_norm`): every chunk
    holds the arm where it is, hand open; it keeps what it was asked and given: the questions' instructions and
    TCP positions, the TCP at each chunk (and its rot6d) and each chunk's release input."""

    cameras, obs_horizon, image_size, execute = ("scene", "wrist"), 1, (128, 128), slice(0, 8)
    manifest = {"horizons": {"control_hz": 10.0}}

    def __init__(self, families=("pick_place",), look=None, turn_deg=None, turn_norm=1.0):
        from policy.goal_query import GoalQuerySpec
        from policy.turn_query import TurnQuerySpec

        self.goal_query = GoalQuerySpec(tuple(families), (0.0, 0.0, 0.05), 3, look is not None, look)
        self.turn_query = None if turn_deg is None else TurnQuerySpec(tuple(families), np.pi / 2)
        self.turn_deg, self.turn_norm, self._turn_from = turn_deg, turn_norm, None
        self.asked, self.asked_at, self.acted_at, self.releases, self.acted_rot = [], [], [], [], []
        self.turns_asked_at = []

    def turn_label(self, images, proprio, emb):
        self.turns_asked_at.append(np.array(proprio[-1, :3]))
        wrist = float(np.arctan2(proprio[-1, 4], proprio[-1, 3]))
        self._turn_from = wrist if self._turn_from is None else self._turn_from
        a = 4.0 * (self._turn_from + np.radians(self.turn_deg) - wrist)
        return self.turn_norm * np.array([np.cos(a), np.sin(a)], np.float32)

    def embed(self, text):
        return np.frombuffer(text.encode().ljust(384)[:384], np.uint8).astype(np.float32)

    def goal_point(self, images, proprio, emb, stage=0):
        self.asked.append(emb)
        self.asked_at.append(np.array(proprio[-1, :3]))
        return np.array([0.1, 0.4 + 0.01 * len(self.asked), 0.02], np.float32)

    def act(self, images, proprio, emb, rng=None, stage=0, **given):
        self.acted_at.append(np.array(proprio[-1, :3]))
        self.acted_rot.append(np.array(proprio[-1, 3:9]))
        self.releases.append(given.get("release"))
        chunk = np.repeat(np.asarray(proprio, np.float32)[-1:, :10], 16, axis=0)
        chunk[:, 9] = 0.0
        return chunk
