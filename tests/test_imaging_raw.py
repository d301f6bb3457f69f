"""Raw 14-bit validation and normalisation: hand values, numpy references, errors (+ under jit)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.imaging.raw import RAW_MAX, check_raw, normalize_raw


def test_check_raw_accepts_14bit_integers():
    check_raw(np.array([[0, RAW_MAX], [5000, 3]], np.uint16))
    check_raw(np.array([[0, 16383]], np.int32))


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros((4, 4), np.uint8), "8-bit"),
        (np.zeros((4, 4), np.float32), "float32"),
        (np.array([[0.0, np.nan]], np.float32), "NaN"),
        (np.array([[0, RAW_MAX + 1]], np.uint16), "exceed 14 bits"),
        (np.array([[-1, 5]], np.int32), ">= 0"),
        (np.zeros((0, 4), np.uint16), "empty"),
    ],
)
def test_check_raw_rejects(bad, message):
    with pytest.raises(ValueError, match=message):
        check_raw(bad)


def test_normalize_fixed_hand_values():
    raw = jnp.array([[0, RAW_MAX, 8191, 1]], jnp.uint16)
    out = normalize_raw(raw, "fixed")
    assert out.dtype == jnp.float32 and out.shape == raw.shape
    np.testing.assert_allclose(out, [[0.0, 1.0, 8191 / 16383, 1 / 16383]], rtol=1e-6)


def test_normalize_percentile_hand_values():
    # values 0..100: the 1st / 99th percentiles are exactly 1 and 99
    raw = jnp.arange(101, dtype=jnp.uint16).reshape(1, 101)
    out = np.asarray(normalize_raw(raw, "percentile", 1.0, 99.0))
    expected = [0.0, 0.0, 49 / 98, 1.0, 1.0]
    np.testing.assert_allclose(out[0, [0, 1, 50, 99, 100]], expected, atol=1e-6)


@pytest.mark.parametrize("shape", [(3, 20, 30), (3, 20, 30, 1)])
def test_normalize_percentile_is_per_image(shape):
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 4000, shape).astype(np.uint16)
    raw[1] += 9000  # a different range for the second image
    out = np.asarray(jax.jit(lambda r: normalize_raw(r, "percentile", 2.0, 97.0))(raw))
    for b in range(shape[0]):
        img = raw[b].astype(np.float64)
        lo, hi = np.percentile(img, 2.0), np.percentile(img, 97.0)
        np.testing.assert_allclose(out[b], np.clip((img - lo) / (hi - lo), 0, 1), atol=1e-5)


def test_normalize_constant_frame_gives_zeros():
    out = normalize_raw(jnp.full((2, 8, 8), 4321, jnp.uint16), "percentile")
    assert np.isfinite(out).all() and not np.asarray(out).any()


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_normalize_rejects_static_dtypes_under_jit(dtype):
    with pytest.raises(ValueError, match="expected a raw 14-bit frame"):
        jax.jit(normalize_raw)(jnp.zeros((4, 4), dtype))


def test_normalize_unknown_mode():
    with pytest.raises(ValueError, match="unknown mode"):
        normalize_raw(jnp.zeros((4, 4), jnp.uint16), "log")


def test_check_raw_16_bits():
    full = np.array([[0, 2**16 - 1], [17899, 19192]], np.uint16)
    check_raw(full, bits=16)
    with pytest.raises(ValueError, match=r"exceed 14 bits: maximum 65535 > 16383 .*"
                                         r"data\.raw_bits=16.*--raw-bits 16"):
        check_raw(full)
    with pytest.raises(ValueError, match=r"exceed 16 bits: maximum 70000 > 65535$"):
        check_raw(np.array([[0, 70000]], np.int32), bits=16)
    with pytest.raises(ValueError, match="expected a raw 16-bit frame .*8-bit"):
        check_raw(np.zeros((2, 2), np.uint8), bits=16)
    with pytest.raises(ValueError, match="bit depth 12"):
        check_raw(full, bits=12)


def test_normalize_fixed_16_bits_hand_formula():
    raw = np.array([[0, 65535, 17899, 19192, 16383]], np.uint16)
    out = np.asarray(jax.jit(lambda r: normalize_raw(r, "fixed", bits=16))(raw))
    np.testing.assert_allclose(out, raw.astype(np.float64) / (2**16 - 1), rtol=1e-6)
    with pytest.raises(ValueError, match="expected a raw 16-bit frame"):
        normalize_raw(jnp.zeros((4, 4), jnp.float32), "fixed", bits=16)
