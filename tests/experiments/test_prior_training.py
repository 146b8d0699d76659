"""Training the learned prior: batches, determinism by seed, resume = uninterrupted."""

from __future__ import annotations

import dataclasses

import torch

from dipnet.experiments.prior_training import TrainConfig, random_batch, train
from dipnet.solvers.denoiser import load_weights

TINY = TrainConfig(train_seeds=(5000, 5002), val_seeds=(5002, 5003), n=16, dips=8, solver_iterations=10, channels=2,
                   steps=6, batch=2, crop=8, checkpoint_every=3)


def test_batches_flip_and_permute_input_and_target_alike():
    vol = torch.arange(16.0**3).reshape(1, 16, 16, 16)
    x, y = random_batch(vol, vol * 2, 3, 8, torch.Generator().manual_seed(0))
    assert x.shape == (3, 1, 8, 8, 8) and torch.equal(y, 2 * x)


def test_training_is_deterministic_and_resume_continues_the_same_run(tmp_path):
    cache = tmp_path / "pairs"
    meta = train(TINY, tmp_path / "a.pt", cache, progress=False)
    assert meta["steps_done"] == 6 and meta["config"]["seed"] == 0
    stopped = train(dataclasses.replace(TINY, max_minutes=0.0), tmp_path / "b.pt", cache, progress=False)
    assert stopped["steps_done"] == 3  # stopped at its first checkpoint
    resumed = train(TINY, tmp_path / "b.pt", cache, resume=True, progress=False)
    assert resumed["steps_done"] == 6
    a, _ = load_weights(tmp_path / "a.pt")
    b, _ = load_weights(tmp_path / "b.pt")
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(p, q), name
