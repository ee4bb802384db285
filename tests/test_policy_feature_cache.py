"""feature_cache: the frozen image encoders run once over the frames, and training reads their features."""

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from policy.config import load_policy_config
from policy.data import PolicyDataset
from policy.feature_cache import image_feature_table
from policy.model import DiffusionPolicy
from policy.testing import TINY, hash_embedder, synthetic_dataset
from policy.train import train
from sim.config import ConfigError

FROZEN = {"aux_target_weight": 1.0, "aux_target_frame": "tcp", "action_frame": "tcp", "aux_condition": True,
          "freeze_pretrained": True}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return synthetic_dataset(tmp_path_factory.mktemp("fcache") / "data", episodes=4, smooth=True)


def test_config_needs_frozen_encoders_and_one_instruction_per_episode():
    with pytest.raises(ConfigError, match="feature_cache 2 needs freeze_pretrained"):
        load_policy_config(TINY, {**FROZEN, "freeze_pretrained": False, "feature_cache": 2})
    with pytest.raises(ConfigError, match="subtask_language_prob = 0"):
        load_policy_config(TINY, {**FROZEN, "feature_cache": 2, "subtask_language_prob": 0.5})


def test_cached_features_give_the_loss_the_images_give(data_dir):
    cfg = load_policy_config(TINY, {**FROZEN, "obs_horizon": 2, "feature_cache": 3})
    torch.manual_seed(0)
    model = DiffusionPolicy(cfg).eval()
    with_images = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder)
    table = image_feature_table(model, with_images, copies=3, seed=5, progress=False)
    n = with_images.num_frames
    assert table.shape == (3 * n, 2 * cfg.image_feature_dim) and n == sum(with_images.lengths)
    assert not torch.allclose(table[:n], table[n:2 * n]) and not torch.allclose(table[n:2 * n], table[2 * n:])
    again = image_feature_table(model, with_images, copies=3, seed=5, progress=False)
    assert torch.equal(table, again)  # the copies are drawn from the seed

    # Unaugmented samples (train=False: centre crop, no jitter) read copy 0: the same loss as from the images.
    named = PolicyDataset(data_dir, cfg, train=False, embedder=hash_embedder, normalizer=with_images.normalizer,
                          read_images=False)
    # it holds no frames (the table's one pass reads them from the store) and builds the same table
    assert named.images is None and with_images.images is not None
    assert torch.equal(image_feature_table(model, named, copies=3, seed=5, progress=False), table)
    picks = [0, 7, len(named) - 1]  # the last one repeats an episode's last frame (clamped window)
    a = default_collate([with_images[i] for i in picks])
    b = default_collate([named[i] for i in picks])
    assert "images" not in b and b["frames"].shape == (3, 2) and int(b["frames"].max()) < n
    b["image_features"] = table[b.pop("frames")]
    noise, t = torch.randn(3, cfg.pred_horizon, cfg.action_dim), torch.tensor([2, 40, 95])
    with torch.no_grad():
        torch.testing.assert_close(model.loss(b, noise, t), model.loss(a, noise, t), atol=1e-5, rtol=1e-5)

    # Training samples pick a random copy: every copy gets drawn.
    shuffled = PolicyDataset(data_dir, cfg, train=True, embedder=hash_embedder, normalizer=with_images.normalizer,
                             read_images=False)
    copies = {int(shuffled[(5, s)]["frames"][0]) // n for s in range(40)}
    assert copies == {0, 1, 2}


def test_training_on_cached_features_keeps_the_encoders_and_learns_the_rest(data_dir, tmp_path):
    from policy.train import load_run_model

    source = tmp_path / "source"
    train(data_dir, dict(TINY), source, steps=3, embedder=hash_embedder, progress=False, threads=1,
          overrides={k: v for k, v in FROZEN.items() if k != "freeze_pretrained"})
    run = tmp_path / "run"
    summary = train(data_dir, dict(TINY), run, steps=12, embedder=hash_embedder, progress=False, threads=1,
                    overrides={**FROZEN, "feature_cache": 2}, init_from=source)
    assert np.isfinite(summary["final_loss"])
    before, _, _ = load_run_model(source)
    after, _, _ = load_run_model(run)
    for name, p in before.state_dict().items():
        if name.startswith(("obs_encoder.images.", "aux_head.")):
            torch.testing.assert_close(after.state_dict()[name], p)
    assert not torch.equal(after.state_dict()["obs_encoder.proprio.0.weight"],
                           before.state_dict()["obs_encoder.proprio.0.weight"])
    # train_aux_head: the encoders stay as the source left them, the aux head learns on the episodes
    head_run = tmp_path / "head"
    train(data_dir, dict(TINY), head_run, steps=12, embedder=hash_embedder, progress=False, threads=1,
          overrides={**FROZEN, "feature_cache": 2, "train_aux_head": True}, init_from=source)
    trained, _, _ = load_run_model(head_run)
    for name, p in before.state_dict().items():
        if name.startswith("obs_encoder.images."):
            torch.testing.assert_close(trained.state_dict()[name], p)
    assert any(not torch.equal(trained.state_dict()[n], p) for n, p in before.state_dict().items()
               if n.startswith("aux_head."))


def test_train_aux_head_needs_a_frozen_run_with_an_aux_head():
    with pytest.raises(ConfigError, match="train_aux_head needs freeze_pretrained"):
        load_policy_config(TINY, {**FROZEN, "freeze_pretrained": False, "train_aux_head": True})
    assert load_policy_config(TINY, {**FROZEN, "train_aux_head": True}).train_aux_head
