"""One step written with an axis name gives the same update on 1 device, shard_map and pmap."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from irdepth_jax.errors import RunError
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.state import TrainState
from irdepth_jax.train.steps import make_train_step


class Toy(nn.Module):
    """Dense -> BatchNorm (synchronised over `axis_name`) -> ReLU -> Dense."""

    axis_name: str | None = None
    use_bn: bool = True

    @nn.compact
    def __call__(self, x, train: bool):
        x = nn.Dense(8)(x)
        if self.use_bn:
            x = nn.BatchNorm(use_running_average=not train, momentum=0.9,
                             axis_name=self.axis_name)(x)
        return nn.Dense(1)(nn.relu(x))[..., 0]


def toy_loss(model):
    def loss_fn(params, batch_stats, frozen, batch, rng):
        variables = {"params": params}
        if batch_stats:
            variables["batch_stats"] = batch_stats
            pred, updates = model.apply(variables, batch["x"], train=True,
                                        mutable=["batch_stats"])
            batch_stats = updates["batch_stats"]
        else:
            pred = model.apply(variables, batch["x"], train=True)
        err = (pred - batch["y"]) ** 2
        return jnp.mean(err), ({"mae": jnp.mean(jnp.sqrt(err))}, batch_stats)

    return loss_fn


def make_state(use_bn=True, lr=0.1):
    x = jnp.zeros((2, 3))
    variables = Toy(use_bn=use_bn).init(jax.random.PRNGKey(0), x, train=False)
    tx = optax.sgd(lr)
    return TrainState.create(variables["params"], variables.get("batch_stats", {}), tx,
                             jax.random.PRNGKey(1), {"all": lambda s: jnp.float32(lr)})


def make_batch(n=16, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)).astype(np.float32)
    y = (x @ np.array([1.0, -2.0, 0.5], np.float32) + 0.3 * x[:, 0] ** 2).astype(np.float32)
    return {"x": x, "y": y}


def run(mode, use_bn=True, accum=1, steps=2, devices=4):
    dp = DataParallel(mode, num_devices=devices)
    step = dp.train_step(make_train_step(toy_loss(Toy(dp.axis_name, use_bn)), dp.axis_name, accum))
    state = dp.replicate(make_state(use_bn))
    history = []
    for i in range(steps):
        state, metrics = step(state, dp.shard_batch(make_batch(seed=i)), None)
        history.append(dp.metrics_to_host(metrics))
    return dp.unreplicate(state), history


def assert_same(a, b, rtol=1e-5, atol=1e-6):
    state_a, hist_a = a
    state_b, hist_b = b
    for ma, mb in zip(hist_a, hist_b):
        for k in ("loss", "mae", "grad_norm"):
            np.testing.assert_allclose(ma[k], mb[k], rtol=rtol, atol=atol, err_msg=k)
    for tree in ("params", "batch_stats", "opt_state"):
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=rtol, atol=atol),
                     getattr(state_a, tree), getattr(state_b, tree))
    assert int(state_a.step) == int(state_b.step)


def test_single_device_step_learns_and_updates_stats():
    state, hist = run("single", steps=3)
    assert hist[0]["lr_all"] == pytest.approx(0.1)
    stats0 = make_state().batch_stats
    moved = jax.tree.map(lambda a, b: float(np.abs(np.asarray(a) - b).max()), state.batch_stats,
                         stats0)
    assert min(jax.tree.leaves(moved)) > 0
    assert int(state.step) == 3


@pytest.mark.multidevice
@pytest.mark.parametrize("mode", ["shard_map", "pmap"])
def test_mapped_step_equals_single_device(four_devices, mode):
    assert_same(run("single"), run(mode))


@pytest.mark.multidevice
def test_gradients_are_not_summed_over_devices(four_devices):
    """With SGD, params_new = params - lr * grad: a 4x gradient would show in the update."""
    single, _ = run("single", steps=1)
    mapped, _ = run("shard_map", steps=1)
    p0 = make_state().params
    def delta(s):
        return jax.tree.leaves(jax.tree.map(lambda a, b: np.asarray(a) - b, s.params, p0))

    for a, b in zip(delta(single), delta(mapped)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
        assert np.abs(a).max() > 0 or np.abs(b).max() == 0


@pytest.mark.multidevice
@pytest.mark.parametrize("mode", ["single", "shard_map", "pmap"])
def test_accumulation_equals_whole_batch_without_batchnorm(four_devices, mode):
    whole = run("single", use_bn=False, accum=1)
    accumulated = run(mode, use_bn=False, accum=4 if mode == "single" else 2)
    assert_same(whole, accumulated)


def test_accumulation_rejects_uneven_split():
    with pytest.raises(ValueError, match="micro-batches"):
        run("single", use_bn=False, accum=3, steps=1)


def test_bad_mode_and_device_count():
    with pytest.raises(ValueError, match="parallel mode"):
        DataParallel("ddp")
    with pytest.raises(RunError, match="^`devices` 64: this machine has"):
        DataParallel("shard_map", num_devices=64)
