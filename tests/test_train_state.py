"""Train states, parameter groups and the optimizers of Stage I-1, I-2 and II; the stage losses."""


import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.source import device_batch
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train.state import TrainState, base_optimizer, label_params, stage1_optimizer, stage2_optimizer
from irdepth_jax.train.steps import make_train_step, stage1_loss_fn, stage1_targets

CFG = get_config("tiny")


@pytest.fixture(scope="module")
def unet_vars():
    return init_unet(CFG)


@pytest.fixture(scope="module")
def batch():
    scenes = [render_scene(i, ("day", "dusk", "night")[i % 3], 32, 48) for i in range(4)]
    out = {k: np.stack([s[k] for s in scenes]) for k in ("raw14", "ir8", "seg")}
    out["seg"][2:] = 255  # two frames without labels (as MS2 frames)
    out["brightness"] = np.ones(4, np.float32)  # as the training loader's augmentation gives it
    return out


def test_label_params_by_path():
    params = {"enc0": {"conv0": {"kernel": 1}}, "dec_seg_up0": {"up": {"kernel": 2}},
              "head_seg": {"kernel": 3}, "dec_recon_up1": {"kernel": 4},
              "head_saturation": {"bias": 5}, "segway": {"kernel": 6}}
    from irdepth_jax.train.state import AUX_BRANCH_PATTERN, SEG_BRANCH_PATTERN
    labels = label_params(params, [(SEG_BRANCH_PATTERN, "seg"), (AUX_BRANCH_PATTERN, "aux")],
                          "shared")
    assert labels == {"enc0": {"conv0": {"kernel": "shared"}},
                      "dec_seg_up0": {"up": {"kernel": "seg"}}, "head_seg": {"kernel": "seg"},
                      "dec_recon_up1": {"kernel": "aux"}, "head_saturation": {"bias": "aux"},
                      "segway": {"kernel": "shared"}}


def test_adadelta_needs_an_explicit_rate_and_descends():
    with pytest.raises(ValueError, match="explicit learning rate"):
        base_optimizer("adadelta", None)
    tx = base_optimizer("adadelta", 1.0)
    x = jnp.array([3.0, -2.0])
    state = tx.init(x)
    for _ in range(50):
        updates, state = tx.update(2 * x, state, x)  # gradient of |x|^2
        x = optax.apply_updates(x, updates)
    assert float(jnp.sum(x ** 2)) < 13.0  # descends (None would have ascended)
    with pytest.raises(ValueError, match="optimizer"):
        base_optimizer("sgd", 0.1)


def _first_update(tx, params):
    """The first update with all-ones gradients (Adam's first step is -lr per coordinate)."""
    grads = jax.tree.map(jnp.ones_like, params)
    updates, _ = tx.update(grads, tx.init(params), params)
    return updates


def test_stage1_i2_group_rates(unet_vars):
    cfg = apply_overrides(CFG, ["stage1.optimizer=adamw", "stage1.weight_decay=0",
                                "stage1.i2_learning_rate=0.01",
                                "stage1.seg_lr_multiplier=10"])
    tx, lr_fns = stage1_optimizer(cfg, "stage1_i2")
    upd = _first_update(tx, unet_vars["params"])
    np.testing.assert_allclose(upd["head_seg"]["kernel"], -0.1, rtol=1e-4)
    np.testing.assert_allclose(upd["dec_seg_up0"]["up"]["kernel"], -0.1, rtol=1e-4)
    np.testing.assert_allclose(upd["enc0"]["conv0"]["kernel"], -0.01, rtol=1e-4)
    np.testing.assert_allclose(upd["head_recon"]["kernel"], -0.01, rtol=1e-4)
    assert float(lr_fns["seg"](0)) == pytest.approx(0.1)
    # single-task: recon / gradient branches not updated (group no_update), the rest as before
    single = apply_overrides(cfg, ["stage1.multitask=false"])
    tx, _ = stage1_optimizer(single, "stage1_i2")
    upd = _first_update(tx, unet_vars["params"])
    assert float(jnp.abs(upd["head_recon"]["kernel"]).max()) == 0.0
    assert float(jnp.abs(upd["dec_grad_up2"]["fuse"]["conv0"]["kernel"]).max()) == 0.0
    np.testing.assert_allclose(upd["head_seg"]["kernel"], -0.1, rtol=1e-4)


def test_optimizers_are_shared_by_equal_runs():
    """Equal configs get the same optimizer object (a static field of TrainState), so a second
    run reuses the first one's compiled train step; another config gets its own."""
    assert stage1_optimizer(CFG, "stage1_i2") is stage1_optimizer(CFG, "stage1_i2")
    assert stage2_optimizer(CFG, 10) is stage2_optimizer(CFG, 10)
    other = apply_overrides(CFG, ["stage1.i2_learning_rate=0.5"])
    assert stage1_optimizer(other, "stage1_i2") is not stage1_optimizer(CFG, "stage1_i2")
    assert stage2_optimizer(CFG, 11) is not stage2_optimizer(CFG, 10)


def test_stage2_rates_and_poly_decay():
    cfg = apply_overrides(CFG, ["stage2.learning_rate=1e-3", "stage2.weight_decay=0"])
    params = {"pretrained": {"w": jnp.zeros(3)}, "depth_head": {"w": jnp.zeros(2)}}
    tx, lr_fns = stage2_optimizer(cfg, total_steps=10)
    upd = _first_update(tx, params)
    np.testing.assert_allclose(upd["pretrained"]["w"], -1e-3, rtol=1e-4)
    np.testing.assert_allclose(upd["depth_head"]["w"], -1e-2, rtol=1e-4)
    for step in (0, 3, 10):
        assert float(lr_fns["backbone"](step)) == pytest.approx(1e-3 * (1 - step / 10) ** 0.9)
    assert float(lr_fns["head"](5)) == pytest.approx(1e-2 * 0.5 ** 0.9)


def test_stage1_targets_by_hand():
    ir8 = np.array([[[0, 51, 51], [255, 255, 255]]], np.uint8)
    recon, sat = stage1_targets(ir8, grad_scale=0.5)
    np.testing.assert_allclose(recon[0, ..., 0], ir8[0] / 255.0)
    # GCM: |dx| + |dy| (forward differences, 0 on the last column / row), / 0.5, clipped
    expected = np.array([[0.2 + 1.0, 0 + 0.8, 0.8], [0, 0, 0]]) / 0.5
    np.testing.assert_allclose(sat[0, ..., 0], np.clip(expected, 0, 1), atol=1e-6)


@pytest.mark.parametrize("phase", ["stage1_i1", "stage1_i2"])
def test_stage1_step_is_finite_and_learns(unet_vars, batch, phase):
    tx, lr_fns = stage1_optimizer(apply_overrides(CFG, ["stage1.learning_rate=3e-3"]), phase)
    state = TrainState.create(unet_vars["params"], unet_vars["batch_stats"], tx,
                              jax.random.PRNGKey(0), lr_fns)
    step = jax.jit(make_train_step(stage1_loss_fn(CFG, phase), None, CFG.stage1.accum_steps))
    # the arrays the training loop feeds, placed as it places them: the program is then the one
    # the --quick tables train with (the preset at 32x48; one compile, shared by the cache)
    state, inputs = jax.device_put((state, device_batch(batch, phase, CFG)), jax.devices()[0])
    losses = []
    for _ in range(6):
        state, metrics = step(state, inputs, None)
        losses.append(float(metrics["loss"]))
    assert all(np.isfinite(losses)) and np.isfinite(float(metrics["grad_norm"]))
    assert losses[-1] < losses[0]
    # the gradient branch's loss is logged under a name apart from the step's gradient norm
    assert {"recon", "loss_gradient", "grad_norm", "psnr"} <= set(metrics) and "grad" not in metrics
    if phase == "stage1_i2":
        assert float(metrics["ce"]) > 0


def test_unlabelled_frames_add_nothing_to_the_cross_entropy(unet_vars, batch):
    loss_fn = stage1_loss_fn(CFG, "stage1_i2")
    unlabelled = {k: v[2:] for k, v in batch.items()}
    grads, (metrics, _) = jax.jit(jax.grad(loss_fn, has_aux=True))(
        unet_vars["params"], unet_vars["batch_stats"], None, unlabelled, jax.random.PRNGKey(0))
    assert float(metrics["ce"]) == 0.0
    seg_grads = jax.tree.leaves(grads["head_seg"])
    assert all(np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).max() == 0
               for g in seg_grads)
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))
