"""The zarr episode store: exact round trips, appends across sessions, crash safety, corrupt shards, merge."""

import json
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import zarr

from datagen.schema import ACTION_DIM, EPISODE_META_KEYS, PROPRIO_DIM, SCHEMA_VERSION, EpisodeData
from datagen.store import (IMAGE_CHUNK_STEPS, Dataset, SchemaVersionError, ShardWriter, StoreError,
                           shard_dir)


def random_episode(task: str, seed: int, T: int, size: int = 16) -> EpisodeData:
    rng = np.random.default_rng(seed + 1000 * len(task))
    meta = {k: None for k in EPISODE_META_KEYS}
    meta.update(task=task, seed=seed, instruction=f"do {task} {seed}", subtasks=["first", "second"],
                success=bool(seed % 2), check_success=True, label={"success": bool(seed % 2), "source": "gt"},
                retries=seed % 3, planner="offline", dr={"friction": np.float64(0.5 + seed), "lights": np.int64(2),
                                                          "colors": np.arange(3)})
    return EpisodeData(
        images={c: rng.integers(0, 256, (T, size, size, 3), dtype=np.uint8) for c in ("scene", "wrist")},
        proprio=rng.normal(size=(T, PROPRIO_DIM)).astype(np.float32),
        action=rng.normal(size=(T, ACTION_DIM)).astype(np.float32),
        subtask=rng.integers(-1, 2, T).astype(np.int16), time=np.arange(T) / 10.0 + rng.random(), meta=meta)


def assert_same(a: EpisodeData, b: EpisodeData) -> None:
    for cam in ("scene", "wrist"):
        assert a.images[cam].dtype == b.images[cam].dtype == np.uint8
        np.testing.assert_array_equal(a.images[cam], b.images[cam])
    for name in ("proprio", "action", "subtask", "time"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y)
    assert json.loads(json.dumps(a.meta, default=lambda v: v.tolist())) == b.meta


def write(root, worker, episodes):
    with ShardWriter(root, worker) as w:
        for ep in episodes:
            w.append(ep)


def test_round_trip_exact(tmp_path):
    eps = [random_episode("pick", s, T) for s, T in enumerate((1, IMAGE_CHUNK_STEPS + 1, 2 * IMAGE_CHUNK_STEPS, 5))]
    write(tmp_path, "w0", eps)
    ds = Dataset(tmp_path)
    assert len(ds) == 4 and ds.num_steps == sum(len(e) for e in eps)
    for i, ep in enumerate(eps):
        assert_same(ep, ds.episode(i))
    rows = ds.episodes()
    assert [(r["task"], r["seed"], r["length"], r["shard"]) for r in rows] == [
        ("pick", s, len(e), "w0") for s, e in enumerate(eps)]
    assert rows[1]["dr"] == {"friction": 1.5, "lights": 2, "colors": [0, 1, 2]}
    assert ds.meta(0)["_schema_version"] == SCHEMA_VERSION
    win = ds.window(2, 3, 11, fields=("action", "wrist_rgb"))
    np.testing.assert_array_equal(win["action"], eps[2].action[3:11])
    np.testing.assert_array_equal(win["wrist_rgb"], eps[2].images["wrist"][3:11])
    steps = list(ds.iter_steps(fields=("subtask",)))
    assert len(steps) == ds.num_steps and steps[1]["episode"] == 1 and steps[1]["step"] == 0
    assert ds.completed_keys() == {("pick", s) for s in range(4)}
    assert zarr.open_array(shard_dir(tmp_path) / "w0.zarr" / "data" / "scene_rgb").chunks == (IMAGE_CHUNK_STEPS, 16, 16, 3)


def test_append_across_sessions_and_one_writer_per_shard(tmp_path):
    eps = [random_episode("stack", s, 7 + s) for s in range(4)]
    write(tmp_path, "w0", eps[:2])
    with ShardWriter(tmp_path, "w0") as w:
        assert w.keys == {("stack", 0), ("stack", 1)}
        with pytest.raises(StoreError, match="another process"):
            ShardWriter(tmp_path, "w0")
        with pytest.raises(StoreError, match="already holds"):
            w.append(eps[0])
        for ep in eps[2:]:
            w.append(ep)
    ds = Dataset(tmp_path)
    assert len(ds) == 4
    for i, ep in enumerate(eps):
        assert_same(ep, ds.episode(i))


def test_crash_between_steps_and_commit_drops_only_the_partial_episode(tmp_path, monkeypatch):
    eps = [random_episode("drawer", s, 9) for s in range(3)]
    write(tmp_path, "w0", eps[:2])

    def crash(self, index, stop):
        raise KeyboardInterrupt("killed after the step arrays were written")

    monkeypatch.setattr(ShardWriter, "_commit", crash)
    with pytest.raises(KeyboardInterrupt), ShardWriter(tmp_path, "w0") as w:
        w.append(eps[2])
    monkeypatch.undo()
    shard = zarr.open_group(shard_dir(tmp_path) / "w0.zarr", mode="r")
    assert shard["data/action"].shape[0] == 27 and shard["meta/episodes"].shape[0] == 3  # the debris is there
    ds = Dataset(tmp_path)  # readers see only committed episodes, without touching the shard
    assert len(ds) == 2 and ds.num_steps == 18
    with ShardWriter(tmp_path, "w0") as w:  # a writer truncates the debris, then regenerates the episode
        assert zarr.open_group(shard_dir(tmp_path) / "w0.zarr", mode="r")["data/action"].shape[0] == 18
        w.append(eps[2])
    ds = Dataset(tmp_path, verify=True)
    assert len(ds) == 3
    for i, ep in enumerate(eps):
        assert_same(ep, ds.episode(i))


def test_crash_after_episode_ends_resized_before_written(tmp_path, monkeypatch):
    eps = [random_episode("drawer", s, 5) for s in range(3)]
    write(tmp_path, "w0", eps[:2])
    monkeypatch.setattr(ShardWriter, "_commit",
                        lambda self, index, stop: self.group["meta/episode_ends"].resize((index + 1,)))
    write(tmp_path, "w0", eps[2:])  # the end entry now holds its fill value
    monkeypatch.undo()
    assert len(Dataset(tmp_path)) == 2
    write(tmp_path, "w0", eps[2:])
    assert Dataset(tmp_path).completed_keys() == {("drawer", s) for s in range(3)}


def test_corrupt_shards_are_named_and_skipped(tmp_path):
    for k in range(4):
        write(tmp_path, f"w{k}", [random_episode("pick", 10 * k + s, 12) for s in range(2)])
    root = shard_dir(tmp_path)
    (root / "w1.zarr" / "meta" / "episode_ends" / "c" / "0").write_bytes(b"garbage, not blosc")
    (root / "w2.zarr" / "zarr.json").unlink()
    chunk = root / "w3.zarr" / "data" / "scene_rgb" / "c" / "1" / "0" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:20])  # truncated image chunk: only decoding finds it
    with pytest.warns(RuntimeWarning) as record:
        ds = Dataset(tmp_path)
    messages = " ".join(str(r.message) for r in record)
    assert "w1" in messages and "w2" in messages and "w3" not in messages
    assert set(ds.shards) == {"w0", "w3"} and set(ds.skipped) == {"w1", "w2"}
    with pytest.raises(StoreError, match="shard w3"):
        ds.episode(2)
    with pytest.warns(RuntimeWarning) as record:
        verified = Dataset(tmp_path, verify=True)
    assert any("shard w3: episode 0 is unreadable" in str(r.message) for r in record)
    assert set(verified.shards) == {"w0"} and len(verified) == 2
    with pytest.raises(StoreError, match="w1"):  # a writer never appends to a corrupt shard
        ShardWriter(tmp_path, "w1")


def test_other_schema_version_is_refused(tmp_path):
    write(tmp_path, "w0", [random_episode("pick", 0, 3)])
    write(tmp_path, "old", [random_episode("pick", 1, 3)])
    g = zarr.open_group(shard_dir(tmp_path) / "old.zarr", mode="a")
    g.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(SchemaVersionError, match=r"shard old .*version"):
        Dataset(tmp_path)


def test_not_a_dataset(tmp_path):
    with pytest.raises(StoreError, match="not a sudd dataset"):
        Dataset(tmp_path / "missing")


def test_merge_equals_union_and_hash_is_stable(tmp_path):
    src, out = tmp_path / "src", tmp_path / "merged"
    by_key = {}
    for k, task in enumerate(("pick", "stack", "drawer")):
        eps = [random_episode(task, s, 4 + s) for s in range(3)]
        write(src, f"w{k}", eps)
        by_key.update({(task, s): e for s, e in enumerate(eps)})
    ds = Dataset(src)
    h = ds.content_hash()
    assert h == Dataset(src).content_hash() == ds.content_hash(verify=True)
    ds.merge(out)
    merged = Dataset(out)
    assert list(merged.shards) == ["merged"] and len(merged) == len(ds) == 9
    assert merged.completed_keys() == ds.completed_keys() == set(by_key)
    for i in range(len(merged)):
        ep = merged.episode(i)
        assert_same(by_key[(ep.meta["task"], ep.meta["seed"])], ep)
    assert merged.content_hash() == h
    ds.merge(out)  # re-running a merge adds nothing
    assert len(Dataset(out)) == 9
    write(src, "w9", [random_episode("pick", 99, 3)])
    assert Dataset(src).content_hash() != h
    with pytest.raises(StoreError, match="new directory"):
        ds.merge(src)


def test_merge_of_some_tasks_swaps_a_family_for_a_new_generation(tmp_path):
    from datagen.merge import merge_datasets

    old, new, out = tmp_path / "old", tmp_path / "new", tmp_path / "out"
    write(old, "w0", [random_episode(t, s, 4) for t in ("pick", "drawer") for s in range(2)])
    fresh = [random_episode("drawer", s, 5) for s in range(2)]  # same seeds, other content
    write(new, "w0", fresh)
    with pytest.raises(StoreError, match="differs"):
        merge_datasets([Dataset(old), Dataset(new)], tmp_path / "refused")
    merge_datasets([Dataset(old)], out, tasks=["pick"])
    assert Dataset(out).completed_keys() == {("pick", 0), ("pick", 1)}
    merged = merge_datasets([Dataset(new)], out)  # into the existing OUT: no conflict, the old drawers left out
    assert merged.completed_keys() == {("pick", 0), ("pick", 1), ("drawer", 0), ("drawer", 1)}
    drawers = [merged.episode(i) for i in range(len(merged)) if merged.meta(i)["task"] == "drawer"]
    for ep in drawers:
        assert_same(fresh[ep.meta["seed"]], ep)


def test_warns_on_a_key_in_two_shards(tmp_path):
    write(tmp_path, "w0", [random_episode("pick", 0, 3)])
    write(tmp_path, "w1", [random_episode("pick", 0, 3)])
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        Dataset(tmp_path)
    assert any("both shard w0 and shard w1" in str(r.message) for r in record)


def test_sigkill_during_appends_never_loses_a_committed_episode(tmp_path):
    """Kill a writer process at arbitrary moments (often mid-append) and check what survives, three times."""
    code = ("import sys; sys.path.insert(0, sys.argv[2]); from test_store import random_episode\n"
            "from datagen.store import ShardWriter\n"
            "w = ShardWriter(sys.argv[1], 'w0'); s = len(w.keys)\n"
            "while True:\n"
            "    w.append(random_episode('pick', s, 40, size=64)); s += 1; print(s, flush=True)\n")
    reported = 0
    for attempt in range(3):
        proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path), str(Path(__file__).parent)],
                                stdout=subprocess.PIPE, text=True)
        for _ in range(2 + attempt):
            reported = int(proc.stdout.readline())  # the episode count it has committed
        time.sleep(0.013 * (attempt + 1))  # land somewhere inside a later append
        proc.kill()
        proc.wait()
        proc.stdout.close()
        ds = Dataset(tmp_path, verify=True)
        assert not ds.skipped and len(ds) >= reported
        assert ds.completed_keys() == {("pick", s) for s in range(len(ds))}
    with ShardWriter(tmp_path, "w0") as w:  # repaired: arrays end exactly at the last commit
        g = zarr.open_group(shard_dir(tmp_path) / "w0.zarr", mode="r")
        assert all(g[f"data/{k}"].shape[0] == w.steps for k in ("scene_rgb", "time"))
        assert g["meta/episodes"].shape[0] == g["meta/episode_ends"].shape[0] == len(w.keys)
    assert_same(random_episode("pick", 0, 40, size=64), Dataset(tmp_path).episode(0))


def test_info_table_and_contact_sheet(tmp_path, capsys):
    import argparse

    from PIL import Image

    from datagen import cli
    from datagen.inspect import dataset_info, format_info

    eps = [random_episode("pick", s, 6 + s) for s in range(4)] + [random_episode("stack", 0, 3)]
    eps[1].meta["check_success"] = False
    write(tmp_path, "w0", eps)
    info = dataset_info(tmp_path)
    assert info["episodes"] == 5 and info["steps"] == sum(len(e) for e in eps)
    pick = info["tasks"]["pick"]
    # success = seed odd (F T F T), check_success (T F T T) agrees once, retries = seed % 3 (0 1 2 0)
    assert pick == {"episodes": 4, "success_rate": 0.5, "mean_length": 7.5, "mean_retries": 0.75,
                    "check_agreement": 0.25}
    assert info["content_hash"] == Dataset(tmp_path).content_hash()
    table = format_info(info)
    assert "pick" in table and "stack" in table and "TOTAL" in table and info["content_hash"] in table

    parser = argparse.ArgumentParser(prog="sudd")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["data", "show", str(tmp_path), "--episode", "2", "--out", str(tmp_path / "ep.png")])
    assert args.func(args) == 0 and "wrote" in capsys.readouterr().out
    with Image.open(tmp_path / "ep.png") as im:
        assert im.width > 10 * 16 and im.height > 2 * 16
    args = parser.parse_args(["data", "info", str(tmp_path), "--json"])
    assert args.func(args) == 0 and json.loads(capsys.readouterr().out)["episodes"] == 5
    args = parser.parse_args(["data", "show", str(tmp_path), "--episode", "7"])
    assert args.func(args) == 2 and "out of range" in capsys.readouterr().err


def test_data_merge_cli_joins_datasets_and_refuses_conflicting_episodes(tmp_path, capsys):
    from runtime.cli import main

    a, b, out = tmp_path / "a", tmp_path / "b", tmp_path / "ab"
    eps_a = [random_episode("pick", s, 4) for s in range(3)]
    eps_b = [random_episode("pick", s, 5) for s in range(3, 5)] + [eps_a[0]]  # one shared, identical episode
    write(a, "w0", eps_a)
    write(b, "w0", eps_b)
    assert main(["data", "merge", str(a), str(b), "--out", str(out)]) == 0
    merged = Dataset(out)
    assert len(merged) == 5 and merged.completed_keys() == {("pick", s) for s in range(5)}
    assert merged.content_hash() in capsys.readouterr().out
    c = tmp_path / "c"
    write(c, "w0", [random_episode("pick", 1, 7)])  # seed 1 again, other content
    assert main(["data", "merge", str(a), str(c), "--out", str(tmp_path / "ac")]) == 2
    assert "('pick', 1) differs" in capsys.readouterr().err
    assert not (tmp_path / "ac").exists()
    assert main(["data", "merge", str(c), "--out", str(out)]) == 2  # conflicts with what --out holds already
    assert "('pick', 1) differs" in capsys.readouterr().err
    assert Dataset(out).content_hash() == merged.content_hash()
    assert main(["data", "merge", str(a), "--out", str(a)]) == 2
