"""Paired augmentation: one draw for every map, labels never interpolated, reproducible."""

import numpy as np
import pytest

from irdepth_jax.data.augment import augment
from irdepth_jax.data.synthetic import render_scene

MAPS = ("raw14", "ir8", "rgb", "depth", "valid", "seg")
OFF = dict(p_crop=0.0, p_brightness=0.0, p_flip=0.0)


@pytest.fixture(scope="module")
def sample():
    s = render_scene(3, "day", 48, 64)
    return dict(raw14=s["raw14"], ir8=s["ir8"], rgb=s["rgb"], depth=s["depth_lidar"],
                valid=s["valid"], seg=s["seg"], id="x", condition="day", labeled=True)


def test_flip_flips_every_map(sample):
    out = augment(sample, np.random.default_rng(0), **{**OFF, "p_flip": 1.0})
    for k in MAPS:
        np.testing.assert_array_equal(out[k], sample[k][:, ::-1])
        assert out[k].dtype == sample[k].dtype
    assert out["id"] == "x" and out["labeled"] is True


def test_nothing_fires_is_identity(sample):
    out = augment(sample, np.random.default_rng(0), **OFF)
    for k in MAPS:
        np.testing.assert_array_equal(out[k], sample[k])


def test_crop_keeps_labels_and_depth_values(sample):
    for seed in range(4):
        out = augment(sample, np.random.default_rng(seed), **{**OFF, "p_crop": 1.0})
        assert set(np.unique(out["seg"])) <= set(np.unique(sample["seg"]))
        assert set(np.unique(out["depth"])) <= set(np.unique(sample["depth"]))
        np.testing.assert_array_equal(out["valid"], out["depth"] > 0)
        for k in MAPS:
            assert out[k].shape == sample[k].shape and out[k].dtype == sample[k].dtype


def test_crop_half_is_a_2x_nearest_zoom_of_the_centre():
    seg = np.arange(64, dtype=np.uint8).reshape(8, 8)
    raw = np.full((8, 8), 7000, np.uint16)
    out = augment(dict(seg=seg, raw14=raw), np.random.default_rng(0),
                  **{**OFF, "p_crop": 1.0}, crop_range=(0.5, 0.5))
    centre = seg[2:6, 2:6]
    np.testing.assert_array_equal(out["seg"], np.repeat(np.repeat(centre, 2, 0), 2, 1))
    np.testing.assert_array_equal(out["raw14"], raw)  # linear resize of a constant stays exact


def test_brightness(sample):
    out = augment(sample, np.random.default_rng(0), **{**OFF, "p_brightness": 1.0},
                  brightness_range=(1.2, 1.2))
    for k in ("ir8", "rgb"):
        want = np.clip(np.rint(sample[k] * 1.2), 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(out[k], want)
    # the counts stay physical; the model applies the same factor to its normalised input
    np.testing.assert_array_equal(out["raw14"], sample["raw14"])
    assert out["brightness"] == np.float32(1.2)
    assert augment(sample, np.random.default_rng(0), **OFF)["brightness"] == 1.0
    for k in ("depth", "seg", "valid"):
        np.testing.assert_array_equal(out[k], sample[k])


def test_reproducible_and_probabilities(sample):
    a = augment(sample, np.random.default_rng(11))
    b = augment(sample, np.random.default_rng(11))
    for k in MAPS:
        np.testing.assert_array_equal(a[k], b[k])
    tiny = dict(seg=np.arange(100, dtype=np.uint8).reshape(10, 10),
                ir8=np.full((10, 10), 100, np.uint8))
    n, flips, crops, bright = 2000, 0, 0, 0
    for seed in range(n):
        out = augment(tiny, np.random.default_rng(seed), crop_range=(0.5, 0.5),
                      brightness_range=(1.2, 1.2))
        flips += out["seg"][0, 0] > out["seg"][0, -1]
        crops += out["seg"].max() < 99
        bright += out["ir8"][0, 0] == 120
    assert abs(flips / n - 0.5) < 0.05
    assert abs(crops / n - 0.1) < 0.03 and abs(bright / n - 0.1) < 0.03


def test_shape_mismatch_is_an_error(sample):
    with pytest.raises(ValueError, match=r"sample\['seg'\] has shape"):
        augment({**sample, "seg": sample["seg"][:10]}, np.random.default_rng(0))
