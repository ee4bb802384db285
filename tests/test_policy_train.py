"""Training: the loss goes down, resume replays an uninterrupted run, DDP (gloo, 2 processes) stays in sync."""

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from policy.config import load_policy_config
from policy.data import PolicyDataset, finish_images
from policy.model import DiffusionPolicy
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import StepBatches, latest_checkpoint, load_run_model, lr_factor, train

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return synthetic_dataset(tmp_path_factory.mktemp("data"), episodes=6, smooth=True)


def _eval_loss(model, data_dir, cfg) -> float:
    ds = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder)
    batch = torch.utils.data.default_collate([ds[i] for i in range(0, len(ds), max(1, len(ds) // 32))])
    g = torch.Generator().manual_seed(123)
    noise = torch.randn(batch["action"].shape, generator=g)
    t = torch.randint(0, cfg.num_train_timesteps, (noise.shape[0],), generator=g)
    with torch.no_grad():
        return float(model.eval().loss(batch, noise, t))


def test_training_reduces_loss_and_writes_run(data_dir, tmp_path):
    cfg = load_policy_config(TINY, {"lr": 3e-3, "warmup_steps": 5, "checkpoint_every": 10, "log_every": 5})
    torch.manual_seed(cfg.seed)
    before = _eval_loss(DiffusionPolicy(cfg), data_dir, cfg)
    run = tmp_path / "run"
    summary = train(data_dir, cfg, run, steps=60, embedder=hash_embedder, progress=False, threads=1)
    model, _, info = load_run_model(run, ema=False)
    after = _eval_loss(model, data_dir, cfg)
    assert after < 0.9 * before, (before, after)  # measured ~0.82 (a tiny net: ~0.5 after 300 steps)
    assert summary["finished"] and summary["step"] == 60 and info["step"] == 60
    for name in ("config.json", "stats.npz", "dataset.json", "metrics.jsonl", "metrics.png", "summary.json"):
        assert (run / name).is_file(), name
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(5, 61, 5))
    assert all({"loss", "lr", "steps_per_s"} <= set(r) for r in rows)
    assert len(list((run / "checkpoints").glob("*.pt"))) == cfg.keep_checkpoints
    ema_model, _, _ = load_run_model(run)  # EMA weights differ from the raw ones but load the same way
    assert any(not torch.equal(a, b) for a, b in zip(ema_model.state_dict().values(), model.state_dict().values()))


def test_resume_replays_an_uninterrupted_run(data_dir, tmp_path):
    kw = dict(embedder=hash_embedder, progress=False, threads=1)
    train(data_dir, dict(TINY), tmp_path / "a", steps=12, **kw)
    stopped = train(data_dir, dict(TINY), tmp_path / "b", steps=12, stop_at=6, **kw)
    assert not stopped["finished"] and latest_checkpoint(tmp_path / "b").name == "step_00000006.pt"
    done = train(data_dir, dict(TINY), tmp_path / "b", steps=12, **kw)
    assert done["finished"] and done["step"] == 12
    for ema in (False, True):
        a, _, _ = load_run_model(tmp_path / "a", ema=ema)
        b, _, _ = load_run_model(tmp_path / "b", ema=ema)
        for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
            torch.testing.assert_close(x, y, atol=1e-6, rtol=1e-5, msg=name)
    la = (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()
    lb = (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["loss"] for x in la] == pytest.approx([json.loads(x)["loss"] for x in lb], rel=1e-5)
    with pytest.raises(ValueError, match="another config"):
        train(data_dir, dict(TINY, lr=5e-4), tmp_path / "b", steps=12, **kw)


def test_a_run_records_its_machine_and_a_resume_elsewhere_says_so(data_dir, tmp_path, monkeypatch, capsys):
    from runtime import machine_record

    kw = dict(embedder=hash_embedder, progress=False, threads=1)
    train(data_dir, dict(TINY), tmp_path / "r", steps=4, stop_at=2, **kw)
    started = json.loads((tmp_path / "r" / "environment.json").read_text())
    assert started["torch"] == torch.__version__ and started["cpu"] == machine_record.cpu_description()
    assert "another machine" not in capsys.readouterr().err
    monkeypatch.setattr(machine_record, "cpu_description", lambda cpuinfo=None: "Other CPU (avx512f)")
    assert train(data_dir, dict(TINY), tmp_path / "r", steps=4, **kw)["finished"]
    assert f"cpu: {started['cpu']} -> Other CPU (avx512f)" in capsys.readouterr().err
    assert json.loads((tmp_path / "r" / "environment.json").read_text()) == started  # where it started is kept


def test_batches_are_a_function_of_the_step():
    a = StepBatches(50, 8, 0, 0, 1, 0, 0)
    b = StepBatches(50, 8, 0, 0, 1, 0, 0)
    assert a.plan(7) == b.plan(7) and a.plan(7) != a.plan(8)
    r0, r1 = StepBatches(50, 8, 0, 0, 2, 0, 0).plan(1), StepBatches(50, 8, 0, 1, 2, 0, 0).plan(1)
    assert not {i for i, _ in r0} & {i for i, _ in r1}  # ranks see disjoint samples
    assert lr_factor(0, 10, 100) == pytest.approx(0.1) and lr_factor(10, 10, 100) == pytest.approx(1.0)
    assert lr_factor(100, 10, 100) == pytest.approx(0.0, abs=1e-12)


def test_ddp_gloo_two_processes_stay_in_sync(data_dir, tmp_path):
    run = tmp_path / "ddp"
    sets = [f"{k}={json.dumps(v)}" for k, v in TINY.items()] + ["batch_size=4", "log_every=1"]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m",
           "policy.train", str(data_dir), str(run), "--steps", "3", "--no-progress", "--device", "cpu"]
    cmd += [a for s in sets for a in ("--set", s)]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1")
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["finished"]
    assert summary["replica_max_diff"] == 0.0  # gradients averaged: identical replicas
    rows = (run / "metrics.jsonl").read_text().splitlines()
    assert len(rows) == 3  # written once (rank 0), not per process
    model, _, info = load_run_model(run)
    assert info["step"] == 3


def test_chunk_error_is_the_distance_of_the_sampled_positions_from_the_recorded(tmp_path, monkeypatch):
    import policy.sampling
    from policy.validate import Validator

    data = synthetic_dataset(tmp_path / "data", episodes=8, smooth=True)
    cfg = load_policy_config(TINY, {"val_fraction": 0.3})
    val = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="val")
    fit = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="train", normalizer=val.normalizer)
    shift = torch.zeros(cfg.action_dim)
    shift[1] = 0.2  # normalized units along y; the other rows and columns exactly as recorded
    recorded = {}

    def fake_sample(model, cond, noise, schedule=None):
        return recorded["action"] + shift

    monkeypatch.setattr(policy.sampling, "sample", fake_sample)
    check = Validator(val, fit, samples=16, batch=8)
    real = check._chunk_cm

    def spy(model, cond, action, g):
        recorded["action"] = action
        return real(model, cond, action, g)

    monkeypatch.setattr(check, "_chunk_cm", spy)
    got = check(DiffusionPolicy(cfg), torch.device("cpu"))
    want = 0.2 / float(val.normalizer.action_scale[1]) * 100
    assert got["val_chunk_cm"] == pytest.approx(want, rel=1e-4) and got["fit_chunk_cm"] == pytest.approx(want, rel=1e-4)


def test_validation_on_several_families_reports_each_familys_medians(tmp_path, monkeypatch):
    from policy.validate import Validator

    data = synthetic_dataset(tmp_path / "data", episodes=8, tasks=("pick_place", "stack"), smooth=True)
    cfg = load_policy_config(TINY, {"val_fraction": 0.3, "aux_target_weight": 1.0})
    val = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="val")
    fit = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="train", normalizer=val.normalizer)
    check = Validator(val, fit, samples=48, batch=8)
    real, per_sample = check._chunk_cm, []
    monkeypatch.setattr(check, "_chunk_cm", lambda *a: per_sample.append(real(*a)) or per_sample[-1])
    got = check(DiffusionPolicy(cfg), torch.device("cpu"))
    ds, idx = check.sets["val"]
    family = np.array([ds.task_of(int(i)) for i in idx])
    assert all(f == ds.store.meta(ds.episodes[ds.index[int(i)][0]])["task"] for f, i in zip(family, idx))
    chunk = np.concatenate(per_sample)[:len(idx)]  # the held-out samples come first
    for f in ("pick_place", "stack"):
        assert got[f"val_chunk_cm.{f}"] == pytest.approx(float(np.median(chunk[family == f])), rel=1e-6)
        assert {f"val_pregrasp_cm.{f}", f"val_release_cm.{f}"} <= set(got) and f"fit_chunk_cm.{f}" not in got
    assert got["val_chunk_cm"] == pytest.approx(float(np.median(chunk)), rel=1e-6)


def test_validation_keeps_whole_episodes_out_and_logs_the_gap(tmp_path):
    from policy.data import episode_success, is_validation
    from policy.validate import Validator

    data = synthetic_dataset(tmp_path / "data", episodes=14, smooth=True)
    cfg = load_policy_config(TINY, {"val_fraction": 0.3, "val_every": 4, "log_every": 4, "aux_target_weight": 1.0})
    val = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="val")
    fit = PolicyDataset(data, cfg, train=False, embedder=hash_embedder, split="train", normalizer=val.normalizer)
    metas = {i: val.store.meta(i) for i in range(len(val.store))}
    ok = [i for i, m in metas.items() if episode_success(m)]
    assert sorted(val.episodes + fit.episodes) == ok and not set(val.episodes) & set(fit.episodes)
    assert val.episodes == [i for i in ok if is_validation(metas[i], 0.3)] != []
    check = Validator(val, fit, samples=16, batch=8)
    model = DiffusionPolicy(cfg)
    first = check(model, torch.device("cpu"))
    assert first == check(model, torch.device("cpu"))  # fixed samples, noise and timesteps
    assert set(first) == {"val_loss", "fit_loss", "val_grasp_cm", "fit_grasp_cm", "guess_grasp_cm",
                          "val_pregrasp_cm", "fit_pregrasp_cm", "val_release_cm", "fit_release_cm",
                          "val_prerelease_cm", "fit_prerelease_cm", "val_chunk_cm", "fit_chunk_cm"}
    # prerelease: the release point's error on the samples before the grasp (where nothing is held over the scene)
    ds, idx = check.sets["val"]
    early = [int(i) for i in idx if ds.before_grasp(int(i))]
    with torch.no_grad():
        b = torch.utils.data.default_collate([ds[i] for i in early])
        b = finish_images(b) if ds.uint8_images else b
        pred = model.eval().aux_points(model.obs_encoder(b["images"], b["proprio"], b["text"]))[:, 3:6].numpy()
    miss = np.linalg.norm(check._metres(pred) - check._metres(b["aux"][:, 3:6].numpy()), axis=1) * 100
    assert first["val_prerelease_cm"] == pytest.approx(float(np.median(miss)), rel=1e-5)
    assert "val_chunk_cm" not in Validator(val, fit, samples=16, batch=8, chunks=False)(model, torch.device("cpu"))
    # before the grasp = the newest observed step precedes the gripper's first close command
    for ds, idx in check.sets.values():
        flags, carried = [], []
        for i in idx:
            k, s = ds.index[int(i)]
            shut = ds.store.window(ds.episodes[k], fields=("action",))["action"][:, -1] > 0.5
            flags.append(ds.before_grasp(int(i)))
            assert flags[-1] == (s + cfg.obs_horizon - 1 < (np.argmax(shut) if shut.any() else len(shut) - 1))
            # carrying = from the first close up to the next open command
            t_open = np.argmax(shut) + np.argmax(~shut[np.argmax(shut):]) if (~shut[np.argmax(shut):]).any() \
                else len(shut) - 1
            carried.append(ds.carrying(int(i)))
            assert carried[-1] == (np.argmax(shut) <= s + cfg.obs_horizon - 1 < t_open)
        assert any(flags) and not all(flags)
        assert any(carried) and not all(carried) and not any(f and c for f, c in zip(flags, carried))
    for ds in (val, fit):  # the image-free target is the one the samples carry
        assert all(torch.equal(ds.aux_target(i), ds[i]["aux"]) for i in (0, len(ds) // 2, len(ds) - 1))
    assert first["guess_grasp_cm"] > 0
    # The head reads the images even where the denoiser may not: its error is the same with them hidden.
    hidden = DiffusionPolicy(load_policy_config(TINY, {"val_fraction": 0.3, "aux_target_weight": 1.0,
                                                       "action_frame": "tcp", "aux_target_frame": "tcp",
                                                       "aux_condition": True, "image_cond_dropout": 1.0}))
    shown = DiffusionPolicy(replace(hidden.cfg, image_cond_dropout=0.0))
    shown.load_state_dict(hidden.state_dict())
    tcp_val = PolicyDataset(data, hidden.cfg, train=False, embedder=hash_embedder, split="val")
    tcp_fit = PolicyDataset(data, hidden.cfg, train=False, embedder=hash_embedder, split="train",
                            normalizer=tcp_val.normalizer)
    tcp_check = Validator(tcp_val, tcp_fit, samples=16, batch=8)
    a, b = tcp_check(hidden, torch.device("cpu")), tcp_check(shown, torch.device("cpu"))
    assert a["val_grasp_cm"] == b["val_grasp_cm"] and a["val_loss"] != b["val_loss"]

    summary = train(data, cfg, tmp_path / "run", steps=10, embedder=hash_embedder, progress=False, threads=1)
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    checks = [r for r in rows if "val_loss" in r]
    assert [r["step"] for r in checks] == [4, 8, 10]
    assert all(r["val_grasp_cm"] > 0 and r["fit_loss"] > 0 for r in checks)
    assert summary["validation"] == checks[-1]
    from PIL import Image

    with Image.open(tmp_path / "run" / "metrics.png") as im:  # loss, lr and the grasp-point panel
        assert im.size[1] > 3 * 200
    info = json.loads((tmp_path / "run" / "dataset.json").read_text())
    assert info["validation_episodes"] == len(val.episodes) and info["episodes_used"] == len(fit.episodes)
    assert info["gripper_levels"] == [0.0, 1.0]  # the synthetic episodes open and close only
    with pytest.raises(ValueError, match="leaves no val episodes"):
        PolicyDataset(data, load_policy_config(TINY, {"val_fraction": 1e-9}), embedder=hash_embedder, split="val")
