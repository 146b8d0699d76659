"""Torch thread counts: one per sweep job, the user's OMP_NUM_THREADS, else the available cores."""

import pytest
import torch

from dipnet.jobs.threads import available_cores, configure_threads, default_threads


def test_a_sweep_job_takes_one_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    assert default_threads(multirun=True) == 1


def test_a_single_run_takes_omp_num_threads_or_the_cores(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert default_threads(multirun=False) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "zero")
    assert default_threads(multirun=False) == available_cores() >= 1


def test_configure_threads_sets_torch_and_refuses_bad_counts():
    before = torch.get_num_threads()
    try:
        assert configure_threads(2) == 2 and torch.get_num_threads() == 2
        assert configure_threads(None, multirun=True) == 1 and torch.get_num_threads() == 1
        with pytest.raises(ValueError, match="threads must be a positive integer or null, got 0"):
            configure_threads(0)
    finally:
        torch.set_num_threads(before)
