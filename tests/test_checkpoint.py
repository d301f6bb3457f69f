"""Orbax checkpoints: round trip, keep-last-K, interrupted saves, stage and shape checks."""

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.config import get_config
from irdepth_jax.runs.checkpoint import Checkpointer, CheckpointError, restore_model
from irdepth_jax.train.state import TrainState, stage2_optimizer


class Net(nn.Module):
    width: int = 4

    @nn.compact
    def __call__(self, x):
        x = nn.BatchNorm(use_running_average=False)(nn.Dense(self.width, name="Dense_0")(x))
        return nn.Dense(2, name="depth_head")(x)


def make_state(width=4, seed=0):
    variables = Net(width).init(jax.random.PRNGKey(seed), jnp.zeros((2, 3)))
    params = {"pretrained": variables["params"]["Dense_0"],
              "depth_head": variables["params"]["depth_head"]}
    tx, lr_fns = stage2_optimizer(get_config("tiny"), total_steps=10)
    return TrainState.create(params, variables["batch_stats"], tx, jax.random.PRNGKey(seed), lr_fns)


def advanced(state, k=1.0):
    """A state with distinguishable values (as if some steps had run)."""
    grads = jax.tree.map(lambda p: jnp.full_like(p, k), state.params)
    return state.apply_gradients(grads, jax.tree.map(lambda s: s + k, state.batch_stats))


def assert_trees_equal(a, b):
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), a, b)


def test_round_trip_keep_last_and_meta(tmp_path):
    ckpt = Checkpointer(str(tmp_path), "stage2", max_to_keep=2)
    state = make_state()
    saved = {}
    for step in (1, 2, 3):
        state = advanced(state, float(step))
        ckpt.save(step, state, {"data_state": {"epoch": 0, "pos": step}, "config": {"a": (1, 2)}})
        saved[step] = state
    ckpt.wait()
    assert ckpt.all_steps() == [2, 3]
    restored, meta = ckpt.restore(make_state(seed=5))
    assert meta["stage"] == "stage2" and meta["step"] == 3
    assert meta["data_state"] == {"epoch": 0, "pos": 3} and meta["config"] == {"a": [1, 2]}
    assert_trees_equal(restored.params, saved[3].params)
    assert_trees_equal(restored.batch_stats, saved[3].batch_stats)
    assert_trees_equal(restored.opt_state, saved[3].opt_state)
    assert int(restored.step) == int(saved[3].step)
    older, _ = ckpt.restore(make_state(), step=2)
    assert_trees_equal(older.params, saved[2].params)
    ckpt.close()


def test_interrupted_save_leaves_last_good_checkpoint(tmp_path):
    ckpt = Checkpointer(str(tmp_path), "stage2")
    good = advanced(make_state(), 2.0)
    ckpt.save(2, good, {})
    ckpt.wait()
    ckpt.close()
    # What a kill during the save of step 4 leaves behind: orbax's temporary directory with
    # part of the arrays and no commit marker.
    tmp = tmp_path / "4.orbax-checkpoint-tmp-1700000000"
    (tmp / "model").mkdir(parents=True)
    (tmp / "model" / "partial").write_bytes(b"\0" * 100)
    reopened = Checkpointer(str(tmp_path), "stage2")
    assert reopened.latest_step() == 2
    restored, meta = reopened.restore(make_state())
    assert meta["step"] == 2
    assert_trees_equal(restored.params, good.params)
    assert not tmp.exists()  # cleaned up on start
    reopened.close()


def test_wrong_stage_and_shape_are_named(tmp_path):
    ckpt = Checkpointer(str(tmp_path), "stage2")
    ckpt.save(1, make_state(), {})
    ckpt.wait()
    ckpt.close()
    with pytest.raises(CheckpointError, match="'stage2' checkpoint, expected 'stage1_i2'"):
        Checkpointer(str(tmp_path), "stage1_i2").restore(make_state())
    with pytest.raises(CheckpointError,
                       match=r"model: batch_stats/BatchNorm_0/mean has shape \(4,\).*\(8,\)"):
        Checkpointer(str(tmp_path), "stage2").restore(make_state(width=8))
    with pytest.raises(CheckpointError, match="expected 'stage1_i1' or 'stage1_i2'"):
        restore_model(str(tmp_path), ("stage1_i1", "stage1_i2"),
                      make_state().checkpoint_items()["model"])
    with pytest.raises(CheckpointError, match="no finished checkpoint"):
        Checkpointer(str(tmp_path / "empty"), "stage2").restore(make_state())
    with pytest.raises(CheckpointError, match="does not exist"):
        restore_model(str(tmp_path / "nope"), "stage2", {})


def test_restore_model_only(tmp_path, caplog):
    ckpt = Checkpointer(str(tmp_path), "stage1_i2")
    state = advanced(make_state(), 3.0)
    ckpt.save(7, state, {})
    ckpt.wait()
    ckpt.close()
    template = make_state().checkpoint_items()["model"]
    with caplog.at_level("WARNING", logger="absl"):
        model, meta = restore_model(str(tmp_path), "stage1_i2", template)
    assert not [r for r in caplog.records if "read only" in r.getMessage()]  # no orbax noise
    assert meta["step"] == 7
    assert_trees_equal(model["params"], state.params)
    assert os.listdir(tmp_path) == ["7"]
