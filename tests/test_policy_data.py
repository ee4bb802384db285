"""Policy samples from the episode store: windows and padding, success filtering, language, augmentation."""

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from datagen.store import Dataset
from policy.config import load_policy_config
from policy.data import PolicyDataset, episode_success, finish_images
from policy.testing import TINY, hash_embedder, synthetic_dataset


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return synthetic_dataset(tmp_path_factory.mktemp("data"), episodes=6, tasks=("pick_place", "stack"))


@pytest.fixture(scope="module")
def cfg():
    return load_policy_config(TINY, {"color_jitter": 0.0})


def test_success_filtering(data_dir, cfg):
    store = Dataset(data_dir)
    labels = [episode_success(store.meta(i)) for i in range(len(store))]
    assert 0 < sum(labels) < len(labels)  # the synthetic set has both
    ds = PolicyDataset(data_dir, cfg, embedder=hash_embedder)
    assert ds.episodes == [i for i, ok in enumerate(labels) if ok]
    everything = PolicyDataset(data_dir, cfg, embedder=hash_embedder, include_failures=True)
    assert everything.episodes == list(range(len(store)))
    assert episode_success({"label": {"value": False, "source": "check"}, "success": True}) is False
    assert episode_success({"label": {"value": None}, "success": True}) is True


def test_windows_and_padding(data_dir, cfg):
    ds = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder)
    To, Tp, Ta = cfg.obs_horizon, cfg.pred_horizon, cfg.action_horizon
    k = 0
    T = ds.lengths[k]
    starts = [s for kk, s in ds.index if kk == k]
    assert starts[0] == -(To - 1) and starts[-1] == T - Tp + Ta - 1  # pad <= To-1 before, <= Ta-1 after
    raw = Dataset(data_dir).window(ds.episodes[k], fields=("proprio", "action"))
    first = ds[ds.index.index((k, starts[0]))]
    np.testing.assert_allclose(ds.normalizer.unnormalize_proprio(first["proprio"].numpy()),
                               np.repeat(raw["proprio"][:1], To, 0), atol=1e-5)  # repeats the first step
    np.testing.assert_allclose(ds.normalizer.unnormalize_action(first["action"].numpy()),
                               raw["action"][np.clip(np.arange(starts[0], starts[0] + Tp), 0, None)], atol=1e-5)
    last = ds[ds.index.index((k, starts[-1]))]
    acts = ds.normalizer.unnormalize_action(last["action"].numpy())
    s = starts[-1]
    np.testing.assert_allclose(acts[:T - s], raw["action"][s:], atol=1e-5)
    np.testing.assert_allclose(acts[T - s:], np.repeat(raw["action"][-1:], Tp - (T - s), 0), atol=1e-5)
    assert Tp - (T - s) == Ta - 1
    np.testing.assert_allclose(ds.normalizer.unnormalize_proprio(last["proprio"].numpy()),
                               raw["proprio"][s:s + To], atol=1e-5)


def test_sample_shapes_and_ranges(data_dir, cfg):
    ds = PolicyDataset(data_dir, cfg, embedder=hash_embedder)
    x = ds[(3, 7)]
    for c in cfg.cameras:
        assert x["images"][c].shape == (cfg.obs_horizon, 3, *cfg.crop_size) and x["images"][c].dtype == torch.float32
        assert 0.0 <= float(x["images"][c].min()) and float(x["images"][c].max()) <= 1.0
    assert x["proprio"].shape == (cfg.obs_horizon, 16) and x["action"].shape == (cfg.pred_horizon, 10)
    assert x["text"].shape == (384,)
    allacts = np.concatenate(ds.action)
    pos = allacts[:, [0, 1, 2, 9]]
    assert pos.min() >= -1 - 1e-5 and pos.max() <= 1 + 1e-5
    batch = torch.utils.data.default_collate([ds[(i, i)] for i in range(4)])
    assert batch["images"][cfg.cameras[0]].shape[0] == 4


def test_augmentation_is_seeded_and_eval_is_centre_crop(data_dir):
    cfg = load_policy_config(TINY, {"color_jitter": 0.3})
    ds = PolicyDataset(data_dir, cfg, embedder=hash_embedder)
    a, b, c = ds[(5, 1)], ds[(5, 1)], ds[(5, 2)]
    cam = cfg.cameras[0]
    assert torch.equal(a["images"][cam], b["images"][cam])
    assert not torch.equal(a["images"][cam], c["images"][cam])
    ev = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder, normalizer=ds.normalizer)
    k, s = ev.index[5]
    frames = Dataset(data_dir).window(ev.episodes[k], fields=(f"{cam}_rgb",))[f"{cam}_rgb"]
    t = np.clip(np.arange(s, s + cfg.obs_horizon), 0, ev.lengths[k] - 1)
    H, h = cfg.image_size[0], cfg.crop_size[0]
    o = (H - h) // 2
    ref = torch.from_numpy(frames[t, o:o + h, o:o + h]).permute(0, 3, 1, 2).float() / 255
    assert torch.equal(ev[5]["images"][cam], ref)


def test_uint8_samples_finished_per_batch_match_float_samples(data_dir):
    cfg = load_policy_config(TINY, {"color_jitter": 0.3})
    flt = PolicyDataset(data_dir, cfg, embedder=hash_embedder)
    raw = PolicyDataset(data_dir, cfg, embedder=hash_embedder, normalizer=flt.normalizer, uint8_images=True)
    items = [(3, 1), (5, 2), (8, 3)]
    batch = default_collate([raw[i] for i in items])
    assert all(x.dtype == torch.uint8 for x in batch["images"].values())
    done = finish_images(batch)
    assert "jitter" not in done
    for j, item in enumerate(items):
        for cam, x in flt[item]["images"].items():
            assert torch.allclose(done["images"][cam][j], x, atol=1e-6)
    jittered = done["images"][cfg.cameras[0]]
    plain = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder, normalizer=flt.normalizer,
                          uint8_images=True)
    assert torch.equal(plain[(3, 1)]["jitter"], torch.ones(3))  # evaluation never jitters
    assert not torch.equal(jittered[0], jittered[1])


def test_language_embedded_once_per_string(data_dir):
    calls = []

    def embedder(texts):
        calls.append(list(texts))
        return hash_embedder(texts)

    cfg = load_policy_config(TINY, {"subtask_language_prob": 0.5})
    ds = PolicyDataset(data_dir, cfg, embedder=embedder)
    assert len(calls) == 1 and len(calls[0]) == len(set(calls[0]))
    assert set(calls[0]) == {"do pick_place", "do stack", "pick_place part 1", "pick_place part 2",
                             "stack part 1", "stack part 2"}
    rows = {tuple(ds[(i, i)]["text"].numpy().round(5)) for i in range(0, len(ds), 3)}
    assert len(rows) > 2  # root instructions and subtask labels both appear
    info = ds.info()
    assert info["tasks"] == ["pick_place", "stack"] and info["instructions"] == ["do pick_place", "do stack"]
    assert info["content_hash"] == Dataset(data_dir).content_hash()


def test_image_cache_off_reads_the_same(data_dir, cfg):
    cached = PolicyDataset(data_dir, cfg, embedder=hash_embedder)
    streamed = PolicyDataset(data_dir, cfg, embedder=hash_embedder, max_cache_bytes=0)
    assert cached.images is not None and streamed.images is None
    for i in (0, 9, len(cached) - 1):
        for c in cfg.cameras:
            assert torch.equal(cached[(i, 3)]["images"][c], streamed[(i, 3)]["images"][c])


def test_no_successful_episode_is_an_error(tmp_path, cfg):
    synthetic_dataset(tmp_path, episodes=1, tasks=("stack",))
    store = Dataset(tmp_path)
    if episode_success(store.meta(0)):
        pytest.skip("the one synthetic episode happens to be a success")
    with pytest.raises(ValueError, match="verified success"):
        PolicyDataset(tmp_path, cfg, embedder=hash_embedder)


def test_data_holdout_is_the_union_of_what_the_episodes_kept_out():
    from policy.data import data_holdout

    metas = [{"holdout": {"colors": ["purple"], "shapes": []}}, {"holdout": {"colors": ["pink", "purple"]}}, {}]
    assert data_holdout(metas) == {"colors": ["pink", "purple"], "shapes": []}
    assert data_holdout([]) == {"colors": [], "shapes": []}


def test_tcp_frame_aux_target_follows_the_sample_newest_step(data_dir):
    from policy.data import grasp_and_release_per_step, relative_to_tcp

    cfg = load_policy_config(TINY, {"aux_target_weight": 1.0, "aux_target_frame": "tcp"})
    ds = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder)
    raw = Dataset(data_dir)
    seen = set()
    for index in (0, 4, 9, 15):
        k, s = ds.index[index]
        arrays = raw.window(ds.episodes[k], fields=("proprio", "action"))
        now = int(np.clip(s + cfg.obs_horizon - 1, 0, ds.lengths[k] - 1))
        steps = grasp_and_release_per_step(arrays["action"])[now]
        want = relative_to_tcp(arrays["action"][list(steps), :3], arrays["proprio"][now].astype(np.float64))
        got = ds[index]["aux"]
        torch.testing.assert_close(got, want)
        seen.add(tuple(got.tolist()))
    assert len(seen) > 1  # unlike the base-frame target, it changes as the arm moves


def test_no_window_learns_an_injected_failure_and_its_close_is_no_grasp(tmp_path, cfg):
    from datagen.schema import PERTURBED, grasp_and_release_steps
    from datagen.store import ShardWriter
    from datagen.workers import synthetic_episode

    ep = synthetic_episode("pick_place", 0, steps=40)
    ep.meta.update(success=True, label={"success": True, "source": "synthetic"})
    grip = np.zeros(40, np.float32)
    grip[10:14] = 1.0  # closes on air (the injected failure) ...
    grip[24:32] = 1.0  # ... then, after the recovery reopened it, the real grasp until the release at 32
    ep.action[:, -1] = grip
    ep.subtask[11:15] = PERTURBED  # the labels of the steps whose targets the actions 10-13 are
    with ShardWriter(tmp_path, "w0") as w:
        w.append(ep)
    assert grasp_and_release_steps(ep.action) == (10, 14)  # what the close on air would count as
    assert grasp_and_release_steps(ep.action, ep.subtask) == (24, 32)
    ds = PolicyDataset(tmp_path, cfg, train=False, embedder=hash_embedder)
    Tp = cfg.pred_horizon
    starts = [s for _, s in ds.index]
    touching = [s for s in range(-(cfg.obs_horizon - 1), 40) if max(0, s) <= 13 and s + Tp - 1 >= 10]
    assert starts and not set(starts) & set(touching)
    for index in range(len(ds)):  # and no learned chunk closes the gripper before step 24
        s = ds.index[index][1]
        acts = ds.normalizer.unnormalize_action(ds[index]["action"].numpy())
        steps = np.clip(s + np.arange(Tp), 0, 39)
        assert np.all(steps[acts[:, -1] > 0.5] >= 24)
    assert ds.grasp_step == [24] and ds.release_step == [32]


def _gripper(commands) -> np.ndarray:
    action = np.zeros((len(commands), 10), np.float32)
    action[:, -1] = commands
    return action


def test_each_step_heads_for_a_real_grasp_and_the_release_that_put_the_object_in_place():
    from datagen.schema import PERTURBED, grasp_and_release_per_step

    # no injected failure: the one grasp at 2 and its release at 5, for every step
    assert grasp_and_release_per_step(_gripper([0, 0, 1, 1, 1, 0, 0])).tolist() == [[2, 5]] * 7
    assert grasp_and_release_per_step(_gripper([0] * 4)).tolist() == [[3, 3]] * 4  # never closes
    # a close on air (actions 2-3, labels one step later) is neither: the grasp at 6 and release at 9 are
    sub = np.zeros(11, np.int16)
    sub[3:5] = PERTURBED
    missed = grasp_and_release_per_step(_gripper([0, 0, 1, 1, 0, 0, 1, 1, 1, 0, 0]), sub)
    assert missed.tolist() == [[6, 9]] * 11
    # a drop in transit (the open at action 4 is injected): before it, the grasp at 1; after it, the regrasp
    # at 7; throughout, the release at 9 that put the object in place
    sub = np.zeros(11, np.int16)
    sub[5] = PERTURBED
    dropped = grasp_and_release_per_step(_gripper([0, 1, 1, 1, 0, 0, 0, 1, 1, 0, 0]), sub)
    assert dropped[:, 0].tolist() == [1, 1, 1, 1, 7, 7, 7, 7, 7, 7, 7] and set(dropped[:, 1]) == {9}
