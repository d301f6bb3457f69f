import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.losses import (
    cross_entropy_loss,
    multitask_loss,
    reconstruction_loss,
    silog_loss,
    sky_loss,
)


def _finite_grad(fn, x):
    g = jax.jit(jax.grad(fn))(x)
    return bool(jnp.all(jnp.isfinite(g))), g


def test_silog_hand_worked():
    # Valid pixels: pred 1, 2 against target 2, 2 -> d = ln 2, 0.
    pred = jnp.array([[[1.0, 2.0], [5.0, 0.0]]])
    target = jnp.array([[[2.0, 2.0], [7.0, 3.0]]])
    mask = jnp.array([[[True, True], [False, False]]])
    ln2 = math.log(2.0)
    expected = math.sqrt(ln2**2 / 2 - 0.5 * (ln2 / 2) ** 2)
    assert float(jax.jit(silog_loss)(pred, target, mask)) == pytest.approx(expected, rel=1e-6)
    expected_l1 = math.sqrt(ln2**2 / 2 - (ln2 / 2) ** 2)  # = ln2 / 2
    assert float(silog_loss(pred, target, mask, lambd=1.0)) == pytest.approx(expected_l1, rel=1e-5)


def test_silog_pools_the_whole_batch_and_accepts_channel_axis():
    # Image 0: d = ln 2 on one pixel; image 1: d = 0 on three pixels. Pooled over 4 pixels.
    pred = jnp.array([[[1.0, 1.0]], [[3.0, 3.0]]])[..., None]
    target = jnp.array([[[2.0, 9.0]], [[3.0, 3.0]]])[..., None]
    mask = jnp.array([[[True, False]], [[True, True]]])[..., None]
    ln2 = math.log(2.0)
    expected = math.sqrt(ln2**2 / 3 - 0.5 * (ln2 / 3) ** 2)
    assert float(silog_loss(pred, target, mask)) == pytest.approx(expected, rel=1e-5)


def test_silog_scale_invariant_with_lambda_one():
    rng = np.random.default_rng(0)
    target = jnp.asarray(rng.uniform(1, 50, (2, 8, 8)), jnp.float32)
    pred = jnp.asarray(rng.uniform(1, 50, (2, 8, 8)), jnp.float32)
    mask = jnp.asarray(rng.random((2, 8, 8)) > 0.3)
    base = float(silog_loss(pred, target, mask, lambd=1.0))
    scaled = float(silog_loss(3.7 * pred, target, mask, lambd=1.0))
    assert scaled == pytest.approx(base, rel=1e-4)
    # With lambda 0.5 the scale is not free: the loss must change.
    assert float(silog_loss(3.7 * pred, target, mask)) != pytest.approx(
        float(silog_loss(pred, target, mask)), rel=1e-3
    )


def test_silog_perfect_and_empty_have_finite_gradients():
    target = jnp.full((1, 4, 4), 5.0)
    mask = jnp.ones((1, 4, 4), bool)
    assert float(silog_loss(target, target, mask)) == 0.0
    ok, _ = _finite_grad(lambda p: silog_loss(p, target, mask), target)
    assert ok
    empty = jnp.zeros((1, 4, 4), bool)
    pred = jnp.zeros((1, 4, 4))  # log(0) at masked pixels must not leak NaN
    assert float(silog_loss(pred, target, empty)) == 0.0
    ok, g = _finite_grad(lambda p: silog_loss(p, target, empty), pred)
    assert ok and float(jnp.abs(g).max()) == 0.0
    # A ReLU head outputting exactly 0 on a valid pixel: finite loss and gradient.
    ok, _ = _finite_grad(lambda p: silog_loss(p, target, mask), pred)
    assert ok and np.isfinite(float(silog_loss(pred, target, mask)))


def test_sky_loss_per_image_mean_over_images_with_sky():
    pred = jnp.array([[[10.0, 20.0]], [[70.0, 0.0]], [[1.0, 1.0]]])
    sky = jnp.array([[[True, True]], [[True, False]], [[False, False]]])
    ref = 80.0
    # Image 0: (70 + 60) / 2 = 65; image 1: 10; image 2 has no sky and is left out.
    assert float(jax.jit(sky_loss)(pred, sky, ref)) == pytest.approx((65 + 10) / 2)
    l2 = (((70**2 + 60**2) / 2) + 10**2) / 2
    assert float(sky_loss(pred, sky, ref, kind="l2")) == pytest.approx(l2)
    none = jnp.zeros_like(sky)
    assert float(sky_loss(pred, none, ref)) == 0.0
    ok, g = _finite_grad(lambda p: sky_loss(p, none, ref), pred)
    assert ok and float(jnp.abs(g).max()) == 0.0
    with pytest.raises(ValueError, match="kind"):
        sky_loss(pred, sky, ref, kind="huber")


def test_reconstruction_loss():
    pred = jnp.array([0.0, 0.5, 1.0, 0.2])
    target = jnp.array([1.0, 0.0, 1.0, 0.2])
    assert float(reconstruction_loss(pred, target)) == pytest.approx(1.5 / 4)
    assert float(reconstruction_loss(pred, target, kind="l2")) == pytest.approx(1.25 / 4)
    mask = jnp.array([False, True, True, False])
    assert float(reconstruction_loss(pred, target, mask)) == pytest.approx(0.25)
    empty = jnp.zeros(4, bool)
    assert float(reconstruction_loss(pred, target, empty)) == 0.0
    ok, _ = _finite_grad(lambda p: reconstruction_loss(p, target, empty, "l2"), pred)
    assert ok


def test_cross_entropy_hand_worked_with_ignore():
    logits = jnp.array([[[[0.0, 0.0], [2.0, 0.0], [5.0, -5.0]]]])  # (1, 1, 3, 2)
    labels = jnp.array([[[0, 1, 255]]])
    expected = (math.log(2.0) + (math.log(math.exp(2.0) + 1.0))) / 2  # -log softmax
    assert float(jax.jit(cross_entropy_loss)(logits, labels)) == pytest.approx(expected, rel=1e-6)
    ignored = jnp.full((1, 1, 3), 255)
    assert float(cross_entropy_loss(logits, ignored)) == 0.0
    ok, g = _finite_grad(lambda lg: cross_entropy_loss(lg, ignored), logits)
    assert ok and float(jnp.abs(g).max()) == 0.0
    with pytest.raises(ValueError, match="logits"):
        cross_entropy_loss(logits, labels[..., :2])


def test_multitask_loss():
    total, logs = jax.jit(multitask_loss)({"seg": 2.0, "recon": 4.0}, {"seg": 1.0, "recon": 0.1})
    assert float(total) == pytest.approx(2.4)
    assert float(logs["recon_weighted"]) == pytest.approx(0.4)
    assert float(logs["recon"]) == 4.0 and float(logs["total"]) == pytest.approx(2.4)
    with pytest.raises(ValueError, match="sky"):
        multitask_loss({"sky": 1.0}, {"silog": 1.0})


def test_combined_gradient_finite_under_jit_with_empty_masks():
    pred = jnp.zeros((2, 4, 4, 1))
    empty = jnp.zeros((2, 4, 4, 1), bool)

    def loss(p):
        terms = {
            "silog": silog_loss(p, jnp.ones_like(p), empty),
            "sky": sky_loss(p, empty, 80.0),
            "recon": reconstruction_loss(p, jnp.ones_like(p), empty),
        }
        return multitask_loss(terms, {"silog": 1.0, "sky": 0.1, "recon": 0.1})[0]

    ok, g = _finite_grad(loss, pred)
    assert ok and float(jnp.abs(g).max()) == 0.0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_silog_of_a_nonfinite_prediction_is_nan_under_jit(bad):
    target = jnp.full((2, 3, 3), 5.0)
    mask = jnp.ones((2, 3, 3), bool).at[1, 0, 0].set(False)
    loss = jax.jit(silog_loss)
    assert np.isnan(float(loss(jnp.full((2, 3, 3), bad), target, mask)))  # was 0.0 for NaN
    one = target.at[0, 2, 2].set(bad)
    assert np.isnan(float(loss(one, target, mask)))
    # Off the mask (no ground truth there) a non-finite prediction does not count.
    assert float(loss(target.at[1, 0, 0].set(bad), target, mask)) == 0.0
