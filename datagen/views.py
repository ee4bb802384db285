"""Labelled views of heavy-DR task scenes, rendered without physics or planning, to pretrain the policy's
image encoder to find what the instruction names: the object and its bin, the blocks to stack, the drawer's
handle.

Why: in closed loop the distilled policy goes through the motions in the wrong place. Its encoder, trained on
447 episodes, puts the grasp point within 3 cm in scenes it trained on and 8.5 cm off in new ones: it learns
scenes, not objects. An episode costs seconds of planning and simulation for one scene; a view costs two
renders, so the encoder can see many more scenes.

A view: the arm at a pose on the way from home to above the named object (each scene's first view is at
home, where every episode starts), both cameras exactly as the recorder makes them (sensor noise included),
the proprioception, the instruction, and the two points the policy's aux head regresses: where the episode
would close the gripper and where it would open it. Those are the family's anchors (datagen/view_anchors.py:
the object and the bin, the two blocks, the handle) plus offsets in the anchor's frame measured on recorded
episodes of the family (`measure_offsets`: median of the recorded grasp/release target minus the anchor), so
the labels mean what the policy's own aux target means; with them the grasp yaw and the footprint period, for
the grasp-axis label (policy/grasp_axis.py). Carrying views (the pick_place object held on its way to the bin,
`carry`; the stacked block on its way to the other too) are datagen/views_carry.py's.

Shards of `SHARD` scenes of one family are written as they finish (`views_<family>_<first seed>.npz`), so an
interrupted run keeps what it made and a rerun skips the shards already there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from datagen.recorder import Recorder
from datagen.schema import IMAGE_SIZE, episode_success, grasp_and_release_per_step
from datagen.view_anchors import FAMILIES, check_carries
from datagen.views_carry import carry_pose, grasp_in_hand, nearest_half_turn, place_carried, tool_yaw
from datagen.views_stages import (OBJECT_AT_START, label_key, parse_key, set_stage, stage_anchors, stage_index, stages,
                                   start_pose)
from sim.build import build_episode
from sim.kinematics import UnreachableError
from sim.rotations import rotvec_to_matrix
from sim.tasks import Holdout

SHARD = 50
TASK = "pick_place"  # the family of shards rendered before views knew others (they have no "task")


def measure_offsets(dataset_dir: str | Path, task: str = TASK, episodes: int = 60) -> dict:
    """Median (recorded grasp target - grasp anchor) and (release target - release anchor), in metres in the
    anchors' frame (datagen/view_anchors.py), over up to `episodes` successful episodes of `task`, each
    rebuilt from its seed for the anchors. `task` is a label key (datagen/views_stages.py): a family, or
    `family/stage` for a long task's later grasp, measured on that grasp cycle of the episodes that made
    exactly one cycle per stage (a retry's extra cycle would shift the count)."""
    from datagen.store import Dataset

    family, stage = parse_key(task)
    if family not in FAMILIES:
        raise ValueError(f"views know the families {', '.join(FAMILIES)}, not {family!r}")
    store = Dataset(dataset_dir)
    grasp, release = [], []
    for row in store.episodes():
        meta = store.meta(row["index"])
        # a phase cut from another family's episode (policy/phase_data.py) keeps that episode's seed, which
        # does not rebuild its scene
        if meta["task"] != family or not episode_success(meta) or "phase_of" in meta:
            continue
        arrays = store.window(row["index"], fields=("action", "subtask"))
        action = arrays["action"]
        cycles = np.unique(grasp_and_release_per_step(action, arrays["subtask"]), axis=0)
        if stage and len(cycles) != len(stages(family)):
            continue
        close, opened = (int(x) for x in cycles[stage])
        h = meta.get("holdout") or {}
        ep = build_episode(family, meta["seed"], "heavy", meta.get("fidelity", "fast"),
                           holdout=Holdout(tuple(h.get("colors", ())), tuple(h.get("shapes", ()))))
        set_stage(ep, stage)
        a = stage_anchors(ep, stage)
        grasp.append(a.frame.T @ (action[close, :3] - a.grasp))
        release.append(a.frame.T @ (action[opened, :3] - a.release))
        if len(grasp) == episodes:
            break
    if not grasp:
        raise ValueError(f"{dataset_dir}: no successful {family} episode to measure the label offsets of {task} on; "
                         f"record some (sudd datagen --task {family}) or leave {task} out of the views")
    return {"grasp": np.median(grasp, axis=0), "release": np.median(release, axis=0), "episodes": len(grasp)}


def sample_pose(home: np.ndarray, grasp: np.ndarray, yaw: float, rng: np.random.Generator) -> np.ndarray:
    """A TCP pose part-way from home to above the grasp point, turned part-way to the grasp yaw, with noise:
    roughly where an episode's arm is before it closes the gripper."""
    t = rng.uniform() ** 0.7  # more views near the object, where precision matters
    above = grasp + [0.0, 0.0, rng.uniform(0.0, 0.12)]
    p = home[:3, 3] + t * (above - home[:3, 3]) + rng.normal(0.0, [0.03, 0.03, 0.02])
    p[2] = max(p[2], grasp[2])
    home_yaw = tool_yaw(home)
    delta = nearest_half_turn(yaw, home_yaw) - home_yaw
    T = np.eye(4)
    turn = t * delta + rng.normal(0.0, 0.15)
    ax, ay = rng.normal(0.0, 0.05, 2)  # a little tilt
    T[:3, :3] = (rotvec_to_matrix([0.0, 0.0, turn]) @ rotvec_to_matrix([ax, 0.0, 0.0])
                 @ rotvec_to_matrix([0.0, ay, 0.0]) @ home[:3, :3])
    T[:3, 3] = p
    return T


def scene_views(seed: int, views: int, offsets: dict, holdout: Holdout = Holdout(), fidelity: str = "fast",
                image_size: tuple[int, int] = IMAGE_SIZE, carry: int = 0, task: str = TASK, stage: str = "",
                at_home: bool = False, look: tuple[float, float, float] | None = None) -> dict:
    """`views` labelled views of the heavy-DR `task` scene of `seed` (the same seed always gives the same
    views), then for a family that carries an object (pick_place, stack) up to `carry` views with it in the
    closed fingers on its way to the release (datagen/views_carry.py; none when the scene's grasp fails).
    A long task's later `stage` (datagen/views_stages.py) shows the scene as the collector leaves it before
    that grasp, the views on the way there from the last release; `offsets` are that stage's. `at_home`: the
    scene as the episode starts instead (drawer_put's drawer shut, the arm at home), with the labels of the grasp
    whose object lies where it starts (views_stages.OBJECT_AT_START: where it will be taken from and put), for a
    question asked at the start (policy/goal_locator.py's object locator).
    `look`: the first view with the TCP moved this far from home (base frame, metres; its orientation kept), the
    pose a goal query looks from (policy/goal_query.py: where home's wrist camera misses part of the table)."""
    if carry:
        check_carries(task)
    look = look if look is not None and any(look) else None  # (0, 0, 0) is home
    index = stage_index(task, stage)
    ep = build_episode(task, seed, "heavy", fidelity, holdout=holdout)
    world = ep.world
    rng = np.random.default_rng([int(seed), 0x71E5, index] if index else [int(seed), 0x71E5])
    if at_home and index != OBJECT_AT_START.get(task):
        raise ValueError(f"at_home views label an object's grasp from the start; {task}'s {stage or 'first'} grasp "
                         "is not one whose object is where it starts (drawer_put's object is, and drawer_stow's)")
    start_state = world.data.qpos.copy(), world.data.qvel.copy()
    set_stage(ep, index)
    a = stage_anchors(ep, index)
    yaw = a.yaw
    grasp, release = a.points(offsets)
    if at_home:  # back to the start: the object lies where it did, the drawer is shut again
        world.data.qpos[:], world.data.qvel[:] = start_state
        world.forward()
    recorder = Recorder(ep, image_size=image_size)
    kin = recorder.kin
    q_home = world.arm_q()
    start = start_pose(ep, kin.fk(q_home), 0 if at_home else index)
    try:
        if index and not at_home:
            try:  # where the last release left the arm; home if that is out of reach
                q_home = kin.ik(start, q_home)
            except UnreachableError:
                pass
            world.data.qpos[world.arm_qpos_adr] = q_home
            world.set_arm_target(q_home)
            world.forward()
        if look is not None:
            _arm_to_look(world, kin, q_home, look)
        recorder.sample()
        if look is not None:
            _set_arm(world, q_home)
        for _ in range(views - 1):
            for _attempt in range(5):
                try:
                    q = kin.ik(sample_pose(start, grasp, yaw, rng), q_home)
                    break
                except UnreachableError:
                    continue
            else:
                continue
            world.data.qpos[world.arm_qpos_adr] = q
            world.set_arm_target(q)
            world.forward()
            recorder.sample()
        if carry:
            _carry_views(ep, recorder, seed, carry, a.carried, grasp, release, yaw, q_home)
        images, proprio = recorder.observations()
    finally:
        recorder.close()
    n = len(proprio)
    return {"scene": images["scene"], "wrist": images["wrist"], "proprio": proprio,
            "points": np.tile(np.stack([grasp, release]).astype(np.float32), (n, 1, 1)),
            "grasp_yaw": np.full(n, yaw, np.float32), "footprint_period": np.full(n, a.period, np.float32),
            "frame": np.tile(a.frame.astype(np.float32), (n, 1, 1)), "task": [task] * n, "stage": [stage] * n,
            "seed": np.full(n, seed, np.int64), "instruction": [ep.instruction] * n,
            "at_home": np.full(n, bool(at_home)),
            "look": np.tile(np.asarray(look if look is not None else (0.0, 0.0, 0.0), np.float32), (n, 1))}


def look_view(task: str, seed: int, look, holdout: Holdout = Holdout(), fidelity: str = "fast", dr: str = "heavy",
              image_size: tuple[int, int] = IMAGE_SIZE) -> tuple[dict, np.ndarray]:
    """The `task` scene of `seed` as its episode starts, seen with the TCP at home + `look`: ({camera: (1, H, W, 3)
    uint8}, (1, PROPRIO_DIM) proprio), as `scene_views(..., look=look)` renders its first view."""
    ep = build_episode(task, seed, dr, fidelity, holdout=holdout)
    recorder = Recorder(ep, image_size=image_size)
    try:
        _arm_to_look(ep.world, recorder.kin, ep.world.arm_q(), look)
        recorder.sample()
        return recorder.observations()
    finally:
        recorder.close()


def look_pose(home: np.ndarray, look) -> np.ndarray:
    """The 4x4 TCP pose `look` (x, y, z metres, base frame) from the `home` pose, its orientation kept."""
    T = np.array(home, np.float64, copy=True)
    T[:3, 3] += np.asarray(look, np.float64)
    return T


def _arm_to_look(world, kin, q_home, look) -> None:
    """The arm from `q_home` to the TCP pose `look` away (look_pose), the IK seeded at home."""
    _set_arm(world, kin.ik(look_pose(kin.fk(q_home), look), q_home))


def _set_arm(world, q) -> None:
    world.data.qpos[world.arm_qpos_adr] = q
    world.set_arm_target(q)
    world.forward()


def _carry_views(ep, recorder, seed: int, views: int, target: str, grasp, release, yaw: float, q_home) -> None:
    rng = np.random.default_rng([int(seed), 0xCA77])  # its own stream: the approach views stay as they were
    yaw = nearest_half_turn(yaw, tool_yaw(recorder.kin.fk(q_home)))  # as the collector turns the wrist least
    in_tcp = grasp_in_hand(ep.world, recorder.kin, target, grasp, yaw, q_home)
    if in_tcp is None:
        return
    q = ep.world.arm_q()
    for _ in range(views):
        for _attempt in range(5):
            try:
                q = recorder.kin.ik(carry_pose(grasp, release, yaw, rng), q)
                break
            except UnreachableError:
                continue
        else:
            continue
        place_carried(ep.world, recorder.kin, q, target, in_tcp)
        recorder.sample()


def generate(out_dir: str | Path, seeds: range, views: int, offsets: dict, holdout: Holdout = Holdout(),
             progress: bool = True, image_size: tuple[int, int] = IMAGE_SIZE, carry: int = 0,
             task: str = TASK, stage: str = "", at_home: bool = False,
             look: tuple[float, float, float] | None = None) -> list[Path]:
    """Render views of every seed's `task` scene (on the way to its grasp `stage`, datagen/views_stages.py) into
    shards of SHARD scenes under out_dir; returns the shards."""
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shards = []
    starts = range(seeds.start, seeds.stop, SHARD)
    key = label_key(task, stage)
    bar = tqdm(total=len(seeds), desc=f"views {key}", unit="scene", disable=not progress)
    for start in starts:
        kind = ("-home" if at_home else "") + ("-look" if look is not None and any(look) else "")
        path = out / f"views_{key.replace('/', '-')}{kind}_{start:08d}.npz"
        chunk = range(start, min(start + SHARD, seeds.stop))
        if not path.exists():
            parts = []
            for seed in chunk:
                parts.append(scene_views(seed, views, offsets, holdout, image_size=image_size, carry=carry, task=task,
                                         stage=stage, at_home=at_home, look=look))
                bar.update(1)
            text = ("instruction", "task", "stage")
            merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k not in text}
            for k in text:
                merged[k] = np.array([t for p in parts for t in p[k]])
            tmp = out / f".{path.stem}.partial.npz"  # hidden from load()'s glob until complete
            np.savez(tmp, offset_grasp=offsets["grasp"], offset_release=offsets["release"], **merged)
            tmp.rename(path)
        else:
            bar.update(len(chunk))
        shards.append(path)
    bar.close()
    return shards


def _shards(views_dir: str | Path | list) -> list[Path]:
    dirs = [views_dir] if isinstance(views_dir, (str, Path)) else list(views_dir)
    paths = []
    for d in dirs:
        found = sorted(Path(d).glob("views_*.npz"))
        if not found:
            raise FileNotFoundError(f"{d}: no views_*.npz shards (make them with `sudd views`)")
        paths += found
    return paths


def _shard_task(shard: dict) -> str:
    return str(shard["task"][0]) if "task" in shard else TASK


def _shard_key(shard: dict) -> str:
    """The shard's label key (datagen/views_stages.py): its family, or family/stage for a later grasp."""
    return label_key(_shard_task(shard), str(shard["stage"][0]) if "stage" in shard else "")


def tasks(views_dir: str | Path | list) -> list[str]:
    """The label keys the views directory (or directories) holds, sorted: the task families, and
    `family/stage` for views of a long task's later grasps (offsets are measured per key)."""
    found = set()
    for path in _shards(views_dir):
        with np.load(path) as shard:
            found.add(_shard_key(shard))
    return sorted(found)


def load(views_dir: str | Path | list, offsets: dict | None = None) -> dict:
    """Every shard of a views directory (or of several), concatenated. With `offsets` ({family:
    measure_offsets of that family's episodes a policy trains on}), the labels are moved from the offsets each
    shard was rendered with to these: the images depend on the grasp point only through the sampled arm
    poses, so the same views serve data whose demonstrations release elsewhere (over a bin's rim instead of
    down in it). Shards from before the families came are pick_place's, in the world frame."""
    parts = [dict(np.load(p)) for p in _shards(views_dir)]
    for p in parts:
        n = len(p["points"])
        task, key = _shard_task(p), _shard_key(p)
        p.setdefault("task", np.array([task] * n))
        p.setdefault("stage", np.array([""] * n))
        p.setdefault("at_home", np.zeros(n, bool))  # shards from before at_home views: on the way to their stage
        p.setdefault("look", np.zeros((n, 3), np.float32))  # shards from before look views: the first view at home
        p.setdefault("frame", np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)))
        if offsets is not None:
            if key not in offsets:
                raise ValueError(f"views of {key} scenes, but no label offsets for {key} (offsets for "
                                 f"{', '.join(sorted(offsets)) or 'no family'}): train on data with {task} episodes")
            new = offsets[key]
            shift = np.stack([new["grasp"] - p["offset_grasp"], new["release"] - p["offset_release"]])
            p["points"] = (p["points"] + np.einsum("nij,kj->nki", p["frame"], shift)).astype(p["points"].dtype)
    keys = set.intersection(*(set(p) for p in parts))  # shards rendered before the grasp yaw was kept lack it
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k in keys and not k.startswith("offset_")}
