import cv2
import numpy as np
import pytest

from irdepth_jax.imaging.tonemap import (
    TONEMAPS,
    camera_like,
    clahe,
    dde,
    double_plateau_he,
    double_plateau_thresholds,
    frequency_denoise,
    guided_filter,
    histogram_equalization,
    linear_tail,
    plateau_he,
)


def _scene(seed=0, h=64, w=80):
    """A raw-like 14-bit frame: vertical gradient, a hot blob, sensor noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    x = 3000 + 800 * yy / h + 900 * np.exp(-((yy - 20) ** 2 + (xx - 50) ** 2) / 60.0)
    return (x + rng.normal(0, 12, (h, w))).astype(np.uint16)


def _smooth_8bit(seed=0, h=60, w=80):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), 2)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)


@pytest.mark.parametrize("name", sorted(TONEMAPS))
def test_outputs_uint8_full_range_same_shape(name):
    raw = _scene()
    out = TONEMAPS[name](raw)
    assert out.dtype == np.uint8 and out.shape == raw.shape
    assert out.min() <= 5 and out.max() >= 250, (name, out.min(), out.max())


@pytest.mark.parametrize("name", sorted(TONEMAPS))
def test_constant_frame_is_mid_grey(name):
    np.testing.assert_array_equal(TONEMAPS[name](np.full((16, 20), 4321, np.uint16)), 128)


@pytest.mark.parametrize("name", sorted(TONEMAPS))
@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((8, 8), np.uint8), "8-bit"),
        (np.zeros((8, 8), np.float32), "float"),
        (np.full((8, 8), np.nan), "NaN"),
        (np.full((8, 8), 20000, np.uint16), "14 bits"),
        (np.zeros((2, 8, 8), np.uint16), "2-D"),
    ],
)
def test_bad_input_raises(name, bad, match):
    with pytest.raises(ValueError, match=match):
        TONEMAPS[name](bad)


@pytest.mark.parametrize("fn", [linear_tail, histogram_equalization])
def test_linear_and_he_are_monotone(fn):
    raw = _scene(1)
    order = np.argsort(raw.ravel(), kind="stable")
    assert np.all(np.diff(fn(raw).ravel()[order].astype(int)) >= 0)


def test_linear_tail_hand_worked():
    raw = np.arange(100, dtype=np.uint16).reshape(10, 10) * 7  # levels 0, 7, ..., 693
    out = linear_tail(raw, 1, 99)
    # Inverted-CDF percentiles of 100 equal-count levels: 1 % -> level 0, 99 % -> level 98 * 7.
    assert out[0, 0] == 0 and out[9, 8] == 255 and out[9, 9] == 255
    assert out[4, 9] == round(49 * 255 / 98)  # 127.5 -> 128 (half to even)
    assert out[2, 0] == round(20 * 255 / 98)


def test_he_equals_opencv_equalize_hist():
    # Equivalence tested: HE depends only on the ranks of the levels, so for raw = 64 * v + 5
    # (v an 8-bit image, any increasing map would do) our 16384-bin HE equals
    # cv2.equalizeHist(v); and directly for raw = v.
    for seed in range(3):
        v = _smooth_8bit(seed)
        ref = cv2.equalizeHist(v)
        np.testing.assert_array_equal(histogram_equalization(v.astype(np.uint16)), ref)
        np.testing.assert_array_equal(histogram_equalization(v.astype(np.uint16) * 64 + 5), ref)


def test_plateau_he():
    raw = _scene(2)
    np.testing.assert_array_equal(plateau_he(raw, np.inf), histogram_equalization(raw))
    # Plateau 1: every occupied level gets the same share, whatever its count.
    raw = np.repeat(np.array([10, 500, 501, 9000], np.uint16), [1, 100, 5, 30])[None, :]
    out = plateau_he(raw, 1)
    np.testing.assert_array_equal(np.unique(out), [0, 85, 170, 255])
    with pytest.raises(ValueError, match="plateau"):
        plateau_he(raw, 0)


def test_double_plateau_thresholds_hand_built():
    hist = np.zeros(16384)
    # Non-zero bins (zeros between them are dropped): 2 9 3 1 7 4 4 12 1.
    hist[[5, 6, 40, 41, 42, 300, 301, 302, 9000]] = [2, 9, 3, 1, 7, 4, 4, 12, 1]
    hist *= 100
    # Local maxima (window 3 or 5): 900, 700, 1200 -> T_up = 2800 / 3.
    # N = 4300, L = 9: T_down = min(4300, 9 * 2800 / 3) / 256 = 4300 / 256.
    for window in (3, 5):
        t_up, t_down = double_plateau_thresholds(hist, window)
        assert t_up == pytest.approx(2800 / 3)
        assert t_down == pytest.approx(4300 / 256)
    # T_up * L < N: one narrow peak among many flat bins. Non-zero bins 1 x 20, 1000 once, 1 x 20.
    h2 = np.zeros(16384)
    h2[100:141] = 1
    h2[120] = 1000
    t_up, t_down = double_plateau_thresholds(h2, 3)
    # Local maxima: 1000, and the flat 1s whose 3-neighbourhood holds no larger value: bins
    # 100..118 and 122..140 (38 of them) plus the edge bins see a padded 0 only.
    assert t_up == pytest.approx((1000 + 38) / 39)
    assert t_down == pytest.approx(min(1040, t_up * 41) / 256)
    assert double_plateau_thresholds(np.zeros(10)) == (0.0, 0.0)
    with pytest.raises(ValueError, match="window"):
        double_plateau_thresholds(hist, 4)


def test_double_plateau_he_hand_worked():
    # Background levels 100 and 102 (1000 px each) around a rare level 101 (2 px).
    raw = np.repeat(np.array([100, 101, 102], np.uint16), [1000, 2, 1000])[None, :]
    # T_up = 1000 (both peaks), T_down = min(2002, 3000) / 256; the rare bin is lifted to
    # T_down: lut(101) = 255 * T_down / (T_down + 1000). Plain HE: 255 * 2 / 1002.
    t_down = 2002 / 256
    out = double_plateau_he(raw)
    assert out[0, 1000] == round(255 * t_down / (t_down + 1000))  # 2
    assert histogram_equalization(raw)[0, 1000] == round(255 * 2 / 1002)  # 1
    assert out[0, 0] == 0 and out[0, -1] == 255


def test_clahe_matches_opencv_8bit():
    # Stated equivalences, for a frame spanning exactly 0..255 (so no quantisation happens):
    # with a clip limit no bin reaches, our 16-bit CLAHE equals OpenCV's 8-bit CLAHE within one
    # grey level; with clipping, within OpenCV's 16-bit excess-spreading difference (docstring).
    v = _smooth_8bit(3, 64, 96)
    for tiles in [(1, 1), (2, 3), (4, 4)]:
        ref = cv2.createCLAHE(clipLimit=1000.0, tileGridSize=(tiles[1], tiles[0])).apply(v)
        ours = clahe(v.astype(np.uint16), clip_limit=1000.0, tiles=tiles)
        assert np.abs(ours.astype(int) - ref).max() <= 1, tiles
    # One tile, no clip: the LUT is 255 * cdf(v) / N (OpenCV's CLAHE does not subtract cdf_min).
    raw = _scene(4)
    cdf = np.cumsum(np.bincount(raw.ravel(), minlength=16384))
    expected = 255.0 * cdf[raw] / raw.size
    got = clahe(raw, clip_limit=1e6, tiles=(1, 1), levels=None)
    assert np.abs(got - expected).max() <= 1.0


def test_clahe_levels_256_is_8bit_clahe_of_the_stretched_frame():
    # Without clipping (the excess spreading differs between OpenCV's 8- and 16-bit paths, see
    # the docstring), levels=256 is OpenCV's 8-bit CLAHE of the quantised min-max stretch.
    raw = _scene(6, 128, 160)
    lo, hi = int(raw.min()), int(raw.max())
    stretched8 = ((raw.astype(np.int64) - lo) * 256 // (hi - lo + 1)).astype(np.uint8)
    ref = cv2.createCLAHE(clipLimit=1000.0, tileGridSize=(8, 8)).apply(stretched8)
    diff = np.abs(clahe(raw, clip_limit=1000.0, levels=256).astype(int) - ref)
    assert diff.max() <= 1


def test_clahe_clip_limit_takes_effect_on_raw_14_bit():
    # Fed raw counts directly, OpenCV's cap is 1 pixel per bin at any clip limit; with our
    # rescale (256x320 frame, 8x8 tiles of 1280 px, 1024 levels) the clip limit must matter.
    raw = _scene(5, 256, 320)
    outs = [clahe(raw, clip_limit=c) for c in (1.0, 2.0, 4.0)]
    assert not np.array_equal(outs[0], outs[1]) and not np.array_equal(outs[1], outs[2])
    # A lower limit means less contrast amplification in the flat, noisy background.
    stds = [float(o[160:, :].std()) for o in outs]
    assert stds[0] < stds[2]
    with pytest.raises(ValueError, match="clip_limit"):
        clahe(raw, clip_limit=0.0)
    with pytest.raises(ValueError, match="levels"):
        clahe(raw, levels=1)


def test_guided_filter_limits():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 100, (32, 40)).astype(np.float32)
    # eps -> 0: a = 1, b = 0, the filter returns the guide itself.
    np.testing.assert_allclose(guided_filter(x, x, 2, 1e-6), x, atol=1e-2)
    # eps -> inf: a = 0, b = local mean; the output is the mean of box means (two box passes).
    def box(im):
        return cv2.boxFilter(im, cv2.CV_32F, (5, 5), borderType=cv2.BORDER_REFLECT)

    np.testing.assert_allclose(guided_filter(x, x, 2, 1e12), box(box(x)), atol=1e-2)
    c = np.full((16, 16), 7.0, np.float32)
    np.testing.assert_allclose(guided_filter(c, c, 3, 1.0), 7.0, atol=1e-4)


def test_frequency_denoise_removes_column_stripes_keeps_scene():
    h, w = 64, 80
    rng = np.random.default_rng(0)
    # Scene: a vertical ramp (a function of y only, i.e. on the kx = 0 line of the spectrum) and
    # a hot object covering a third of the rows of some columns.
    scene = 3000 + 10.0 * np.arange(h)[:, None] * np.ones((1, w))
    scene[20:40, 30:50] += 300
    stripes = rng.normal(0, 20, w)[None, :]
    out = frequency_denoise(scene + stripes)
    clean = frequency_denoise(scene)
    # Column-to-column jumps (the stripes' signature) are mostly removed ...
    residual = (out - clean).mean(axis=0)
    assert np.diff(residual).std() < 0.25 * np.diff(stripes[0]).std()
    # ... and the stripe-free scene is left alone away from the object's edges (low-pass) and
    # the borders (the FFT sees the ramp wrap around as a 630-count step; the Gaussian, cut at
    # Nyquist, rings by ~0.3 % of it a few rows away).
    np.testing.assert_allclose(clean[4:-4, 4:28], scene[4:-4, 4:28], atol=2.0)
    np.testing.assert_allclose(clean[24:36, 34:46], scene[24:36, 34:46], atol=2.0)
    np.testing.assert_allclose(frequency_denoise(scene, destripe=False)[24:36, 34:46],
                               scene[24:36, 34:46], atol=2.0)


def test_dde_and_camera_like_enhance_small_detail():
    # A faint 4x4 hot spot (+20 counts) on a wide smooth ramp (10 counts per column): global
    # mappings give it about 20 * 255 / 1600 = 3 grey levels; detail enhancement must give more.
    yy, xx = np.mgrid[:64, :160]
    raw = 3000 + 1600 * (xx / 160.0)
    raw[30:34, 40:44] += 20
    raw = raw.astype(np.uint16)

    def contrast(img):  # spot vs the same columns a few rows below
        return float(img[30:34, 40:44].mean()) - float(img[38:42, 40:44].mean())

    linear = contrast(linear_tail(raw))
    assert linear == pytest.approx(3.0, abs=1.0)
    assert contrast(dde(raw)) > 1.5 * linear
    assert contrast(camera_like(raw)) > 1.5 * linear
    with pytest.raises(ValueError, match="plateau"):
        dde(raw, plateau=-1.0)


@pytest.mark.parametrize("name", sorted(TONEMAPS))
def test_16_bit_counts(name):
    """A 16-bit camera's frame (counts over 14 bits) is mapped with bits=16; the histogram maps
    depend on the order of the levels only, so counts shifted left by 2 bits map as before."""
    raw14 = _scene()
    raw16 = raw14 << 2
    assert raw16.max() > 2**14 - 1
    out = TONEMAPS[name](raw16, bits=16)
    assert out.dtype == np.uint8 and out.shape == raw16.shape
    assert out.min() <= 5 and out.max() >= 250, (name, out.min(), out.max())
    if name in ("linear", "he", "plateau", "double_plateau"):
        np.testing.assert_array_equal(out, TONEMAPS[name](raw14))
    with pytest.raises(ValueError, match="exceed 16 bits"):
        TONEMAPS[name](raw16.astype(np.int32) + 2**16, bits=16)
