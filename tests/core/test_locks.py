"""Exclusive locks: a second holder is refused naming the first; released locks are free again."""

import os

import pytest

from dipnet.core.locks import CHECKPOINT_LOCK_NAME, HeldLock, LockHeld, checkpoint_directory_lock, run_directory_lock


def test_a_held_lock_refuses_a_second_holder_and_names_the_first(tmp_path):
    first = HeldLock(tmp_path / "x.lock")
    try:
        with pytest.raises(LockHeld, match=f"pid {os.getpid()} on "):
            HeldLock(tmp_path / "x.lock")
    finally:
        first.release()
    first.release()  # idempotent
    HeldLock(tmp_path / "x.lock").release()  # free again


def test_a_run_directory_is_held_for_the_block_only(tmp_path):
    run = tmp_path / "run"
    with run_directory_lock(run):
        assert run.is_dir()
        with pytest.raises(LockHeld), run_directory_lock(run):
            pass
    with run_directory_lock(run):
        pass


def test_a_checkpoint_directory_is_held_for_the_block_only_and_none_holds_nothing(tmp_path):
    with checkpoint_directory_lock(None) as held:
        assert held is None
    with checkpoint_directory_lock(tmp_path / "ck") as held:
        assert held == tmp_path / "ck" and (held / CHECKPOINT_LOCK_NAME).is_file()
        with pytest.raises(LockHeld, match=f"checkpoint directory {tmp_path / 'ck'} is in use by another solve"):
            with checkpoint_directory_lock(tmp_path / "ck"):
                pass
    with checkpoint_directory_lock(tmp_path / "ck"):
        pass
