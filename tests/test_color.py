"""HSV colour: OpenCV parity, class hue palette (soft and argmax), gradients, errors."""

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.config import CLASS_NAMES
from irdepth_jax.imaging.color import CLASS_HUES, class_hue, hsv_compose, hsv_to_rgb


def circular_distance(a, b):
    d = np.abs(np.asarray(a) - np.asarray(b)) % 1.0
    return np.minimum(d, 1.0 - d)


def test_hsv_to_rgb_matches_opencv():
    rng = np.random.default_rng(0)
    hsv = rng.random((3, 40, 50, 3)).astype(np.float32)
    hsv[0, 0, :7, 0] = np.arange(7) / 6 - 1e-7 * (np.arange(7) == 6)  # sector borders
    ours = np.asarray(jax.jit(hsv_to_rgb)(hsv))
    for b in range(3):
        cv_hsv = hsv[b].copy()
        cv_hsv[..., 0] *= 360.0
        ref = cv2.cvtColor(cv_hsv, cv2.COLOR_HSV2RGB)
        np.testing.assert_allclose(ours[b], ref, atol=1e-5)


def test_hsv_to_rgb_gradients_finite_at_sector_borders():
    hue = jnp.arange(7.0)[:, None] / 6
    hsv = jnp.concatenate([hue, jnp.full_like(hue, 0.5), jnp.full_like(hue, 0.8)], axis=-1)
    grad = jax.grad(lambda x: hsv_to_rgb(x).sum())(hsv)
    assert np.isfinite(grad).all()


def test_class_hues_spread_around_circle():
    assert len(CLASS_HUES) == len(CLASS_NAMES) == 6
    hues = np.array(CLASS_HUES)
    assert ((0 <= hues) & (hues < 1)).all()
    pairwise = circular_distance(hues[:, None], hues[None, :]) + np.eye(6)
    np.testing.assert_allclose(pairwise.min(), 1 / 6, atol=1e-7)


def test_class_hue_soft_roundtrips_confident_logits_and_argmax_exact():
    labels = np.random.default_rng(1).integers(0, 6, (2, 5, 7))
    logits = 30.0 * jax.nn.one_hot(labels, 6)
    soft = np.asarray(jax.jit(class_hue)(logits))
    assert soft.shape == (2, 5, 7, 1)
    assert ((0 <= soft) & (soft < 1)).all()
    expected = np.array(CLASS_HUES, np.float32)[labels][..., None]
    assert circular_distance(soft, expected).max() < 1e-5
    noisy = logits + jax.random.normal(jax.random.key(0), logits.shape) * 10
    argmax = class_hue(noisy, mode="argmax")
    expected = np.array(CLASS_HUES, np.float32)[noisy.argmax(-1)]
    np.testing.assert_array_equal(argmax[..., 0], expected)


def test_class_hue_soft_is_the_weighted_circular_mean():
    # hand-worked: car (60 deg) and tree (120 deg) at equal probability -> 90 deg = 0.25
    car, tree = CLASS_NAMES.index("car"), CLASS_NAMES.index("tree")
    logits = jnp.full((1, 1, 1, 6), -1e4).at[..., car].set(0.0).at[..., tree].set(0.0)
    np.testing.assert_allclose(class_hue(logits)[0, 0, 0, 0], 0.25, atol=1e-6)
    # random logits against a complex-number reference
    logits = np.random.default_rng(2).normal(size=(1, 4, 4, 6)).astype(np.float32)
    probs = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    ref = (np.angle(probs @ np.exp(2j * math.pi * np.array(CLASS_HUES))) / (2 * math.pi)) % 1.0
    assert circular_distance(class_hue(logits)[..., 0], ref).max() < 1e-5


def test_class_hue_soft_gradients_finite_even_when_undefined():
    def total(logits):
        return jnp.sum(jnp.sin(2 * math.pi * class_hue(logits)))

    grad_fn = jax.jit(jax.grad(total))
    logits = np.random.default_rng(3).normal(size=(1, 4, 4, 6)).astype(np.float32)
    grad = grad_fn(logits)
    assert np.isfinite(grad).all() and np.abs(grad).sum() > 0
    uniform = np.zeros((1, 4, 4, 6), np.float32)  # unit vectors cancel: hue undefined
    assert np.isfinite(grad_fn(uniform)).all()


def test_class_hue_errors():
    with pytest.raises(ValueError, match="unknown mode"):
        class_hue(jnp.zeros((1, 2, 2, 6)), mode="mean")
    with pytest.raises(ValueError, match="classes"):
        class_hue(jnp.zeros((1, 2, 2, 5)))


def test_hsv_compose():
    h = jnp.array([[[[1.25]]]])
    s = jnp.array([[[[1.5]]]])
    v = jnp.array([[[[-0.1]]]])
    np.testing.assert_allclose(hsv_compose(h, s, v)[0, 0, 0], [0.25, 1.0, 0.0])
    with pytest.raises(ValueError, match="one shape"):
        hsv_compose(h, s, jnp.zeros((1, 1, 2, 1)))
