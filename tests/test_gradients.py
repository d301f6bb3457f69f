"""GCM against a hand-worked example and a numpy reference; resize against scikit-image."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.measure import block_reduce

from irdepth_jax.imaging.gradients import gradient_magnitude, resize_gradient


def numpy_gcm(img):
    """Loop-free numpy reference over the two leading spatial axes of an (H, W, ...) array."""
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, :-1] = np.abs(img[:, 1:] - img[:, :-1])
    gy[:-1, :] = np.abs(img[1:, :] - img[:-1, :])
    return gx + gy


def test_gcm_hand_worked():
    img = jnp.array([[0.0, 1.0, 3.0], [2.0, 2.0, 0.0]])
    # Gx = [[1, 2, 0], [0, 2, 0]], Gy = [[2, 1, 3], [0, 0, 0]]
    np.testing.assert_array_equal(gradient_magnitude(img), [[3.0, 3.0, 3.0], [0.0, 2.0, 0.0]])


def test_gcm_matches_numpy_for_hw_hwc_nhwc():
    rng = np.random.default_rng(0)
    batch = rng.random((2, 9, 11, 3)).astype(np.float32)
    gcm = jax.jit(gradient_magnitude)
    out = np.asarray(gcm(batch))
    for b in range(2):
        np.testing.assert_allclose(out[b], numpy_gcm(batch[b]), atol=1e-6)
        np.testing.assert_allclose(gcm(batch[b]), numpy_gcm(batch[b]), atol=1e-6)
        np.testing.assert_allclose(gcm(batch[b, ..., 0]), numpy_gcm(batch[b, ..., 0]), atol=1e-6)


def test_gcm_gradients_are_finite_on_flat_regions():
    img = jnp.zeros((1, 6, 6, 1)).at[0, 2:4, 2:4, 0].set(1.0)
    grad = jax.grad(lambda x: gradient_magnitude(x).sum())(img)
    assert np.isfinite(grad).all()
    # a background pixel only touches zero differences: a subgradient of |.| at 0 lies in
    # [-1, 1] and the pixel enters two differences
    assert abs(float(grad[0, 0, 0, 0])) <= 2.0
    assert np.abs(grad).sum() > 0


def test_gcm_rejects_integer_and_bad_rank():
    with pytest.raises(ValueError, match="float"):
        gradient_magnitude(jnp.zeros((4, 4), jnp.uint16))
    with pytest.raises(ValueError, match="NHWC"):
        gradient_magnitude(jnp.zeros((1, 1, 4, 4, 1)))


def test_resize_integer_factor_is_block_mean():
    g = np.random.default_rng(1).random((2, 16, 24, 1)).astype(np.float32)
    out = jax.jit(resize_gradient, static_argnums=1)(g, (4, 6))
    np.testing.assert_allclose(out, block_reduce(g, (1, 4, 4, 1), np.mean), atol=1e-6)


def test_resize_non_integer_factor():
    g = jnp.full((1, 10, 10, 1), 0.25)
    out = resize_gradient(g, (7, 13))
    assert out.shape == (1, 7, 13, 1)
    np.testing.assert_allclose(out, 0.25, atol=1e-6)
    assert resize_gradient(g, (10, 10)) is g
