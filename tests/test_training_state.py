"""The loop state: one TrainState, saved as a plain dict; checkpoints of the earlier dict-based
loop (same keys) still resume, and a state that cannot be resumed is refused by name."""

import math

import pytest
import torch

from training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from training.config import TrainConfig
from training.synthetic import make_synthetic_crop_dataset
from training.train import TrainState, train

CFG = dict(batch_size=8, base_lr=0.01, seed=3, log_every_steps=1, val_every_samples=10**6)


def test_state_advances_and_round_trips_through_a_plain_dict():
    st = TrainState()
    st.advance(8)
    st.advance(8)
    st.next_epoch()
    assert (st.step, st.samples_seen, st.epoch, st.batch_in_epoch) == (2, 16, 1, 0)
    d = st.to_dict()
    assert all(isinstance(v, (int, float)) for v in d.values())
    back = TrainState.from_dict(d)
    assert back.step == 2 and math.isnan(back.best_val_balanced_accuracy)


def test_state_lacking_its_position_is_refused_by_name():
    with pytest.raises(CheckpointError, match=r"last.pt: its training state lacks \['batch_in_epoch'\]"):
        TrainState.from_dict({"step": 1, "samples_seen": 8, "epoch": 0}, "run/last.pt")


def test_checkpoint_of_the_dict_based_loop_resumes_to_the_same_weights(tmp_path):
    data = tmp_path / "data"
    make_synthetic_crop_dataset(data, 16, 8, 8, positive_rate=0.5, seed=1)
    train(TrainConfig(samples=24, **CFG), data, tmp_path / "straight", progress=False)
    old = tmp_path / "old"
    train(TrainConfig(samples=8, **CFG), data, old, progress=False)
    last = old / "checkpoints" / "last.pt"
    ck = load_checkpoint(last)
    # exactly the state dict the earlier loop saved (its keys, NaN best, world_size)
    ck["state"] = {
        "step": 1,
        "samples_seen": 8,
        "epoch": 0,
        "batch_in_epoch": 1,
        "best_val_balanced_accuracy": float("nan"),
        "best_step": -1,
        "wall_time_s": 1.5,
        "world_size": 1,
    }
    save_checkpoint(last, ck)
    r = train(TrainConfig(samples=24, **CFG), data, old, resume=True, progress=False)
    a, b = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt"), load_checkpoint(last)
    assert r.steps == 3 and b["state"]["wall_time_s"] >= 1.5
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], rtol=1e-5, atol=1e-6)


def test_resume_from_a_checkpoint_without_position_exits_with_its_path(tmp_path):
    data = tmp_path / "data"
    make_synthetic_crop_dataset(data, 16, 8, 8, positive_rate=0.5, seed=1)
    train(TrainConfig(samples=8, **CFG), data, tmp_path / "r", progress=False)
    last = tmp_path / "r" / "checkpoints" / "last.pt"
    ck = load_checkpoint(last)
    del ck["state"]["epoch"]
    save_checkpoint(last, ck)
    with pytest.raises(CheckpointError, match="lacks"):
        train(TrainConfig(samples=24, **CFG), data, tmp_path / "r", resume=True, progress=False)
