import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from irdepth_jax.image_metrics import confusion_matrix, entropy, mean_iou, per_class_iou, psnr, ssim
from irdepth_jax.metrics import DEPTH_METRICS, DepthMetricAccumulator, depth_metrics, per_image_depth_metrics


def _hand_case():
    """10 valid pixels with gt 2 and pred 2 (x5), 2.5 (x3), 4 (x2), plus 5 invalid pixels."""
    gt = np.full((1, 3, 5), 2.0)
    pred = np.array([[2.0] * 5 + [2.5] * 3 + [4.0] * 2 + [9.0] * 5]).reshape(1, 3, 5)
    mask = np.ones((1, 3, 5), bool)
    gt[0, 2, :4] = [0.0, 100.0, 0.0005, 81.0]  # out of [1e-3, 80]
    mask[0, 2, 4] = False  # no label
    return pred, gt, mask


def test_depth_metrics_hand_worked():
    pred, gt, mask = _hand_case()
    m = depth_metrics(pred, gt, mask)
    ln125, ln2 = math.log(1.25), math.log(2.0)
    # thresh = 1 (x5), 1.25 (x3), 2 (x2); 1.25 is not < 1.25; 2 > 1.25^3 = 1.953.
    assert m["d1"] == pytest.approx(0.5)
    assert m["d2"] == pytest.approx(0.8)
    assert m["d3"] == pytest.approx(0.8)
    assert m["abs_rel"] == pytest.approx((3 * 0.25 + 2 * 1.0) / 10)
    assert m["sq_rel"] == pytest.approx((3 * 0.25 / 2 + 2 * 4.0 / 2) / 10)
    assert m["rmse"] == pytest.approx(math.sqrt((3 * 0.25 + 2 * 4.0) / 10))
    assert m["rmse_log"] == pytest.approx(math.sqrt((3 * ln125**2 + 2 * ln2**2) / 10), rel=1e-5)
    assert m["log10"] == pytest.approx((3 * math.log10(1.25) + 2 * math.log10(2.0)) / 10, rel=1e-5)
    mean_d = (3 * ln125 + 2 * ln2) / 10
    mean_d2 = (3 * ln125**2 + 2 * ln2**2) / 10
    assert m["silog"] == pytest.approx(math.sqrt(mean_d2 - 0.5 * mean_d**2), rel=1e-5)
    assert m["count"] == 1


def test_prediction_clamped_to_max_depth():
    gt = np.full((1, 2, 5), 40.0)
    m = depth_metrics(np.full((1, 2, 5), 1000.0), gt)  # clamped to 80
    assert m["abs_rel"] == pytest.approx(1.0)
    assert m["rmse"] == pytest.approx(40.0)
    assert m["d3"] == 0.0


def test_perfect_prediction():
    gt = np.random.default_rng(0).uniform(1, 80, (3, 6, 7))
    m = depth_metrics(gt, gt)
    assert m["d1"] == m["d2"] == m["d3"] == 1.0
    for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "log10", "silog"):
        assert m[k] == pytest.approx(0.0, abs=1e-5)
    assert m["count"] == 3


@pytest.fixture
def noisy():
    rng = np.random.default_rng(1)
    gt = rng.uniform(2, 60, (3, 8, 9))
    pred = gt * rng.uniform(0.7, 1.4, gt.shape)
    mask = rng.random(gt.shape) > 0.2
    return pred, gt, mask


def test_median_alignment(noisy):
    pred, gt, mask = noisy
    base = depth_metrics(pred, gt, mask, align="median")
    scaled = depth_metrics(0.137 * pred, gt, mask, align="median")
    for k in DEPTH_METRICS:
        assert scaled[k] == pytest.approx(base[k], rel=1e-4, abs=1e-6)
    # A prediction off by one global factor per image becomes perfect.
    factors = np.array([0.5, 2.0, 7.0])[:, None, None]
    m = depth_metrics(gt * factors, gt, mask, align="median")
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-5) and m["d1"] == 1.0


def test_scale_shift_alignment(noisy):
    pred, gt, mask = noisy
    base = depth_metrics(pred, gt, mask, align="scale_shift")
    moved = depth_metrics(3.0 * pred - 5.0, gt, mask, align="scale_shift")
    for k in DEPTH_METRICS:
        assert moved[k] == pytest.approx(base[k], rel=1e-3, abs=1e-5)
    m = depth_metrics(0.25 * gt + 3.0, gt, mask, align="scale_shift")
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-4) and m["d1"] == 1.0
    # Unaligned, the same prediction is wrong.
    assert depth_metrics(0.25 * gt + 3.0, gt, mask)["d1"] < 0.5


def test_images_with_fewer_than_10_valid_pixels_are_skipped():
    pred, gt, mask = _hand_case()
    bad_pred = np.full_like(pred, 50.0)
    few = np.zeros_like(mask)
    few[0, 0, :5] = few[0, 1, :4] = True  # 9 valid pixels
    both = depth_metrics(
        np.concatenate([pred, bad_pred]), np.concatenate([gt, gt]), np.concatenate([mask, few])
    )
    alone = depth_metrics(pred, gt, mask)
    assert both["count"] == 1
    for k in DEPTH_METRICS:
        assert both[k] == pytest.approx(alone[k])
    per = per_image_depth_metrics(bad_pred, gt, few)
    assert not bool(per["used"][0])
    none = depth_metrics(bad_pred, gt, few)
    assert none["count"] == 0 and math.isnan(none["abs_rel"])


def test_accumulator_means_over_images_and_conditions():
    gt = np.full((1, 2, 5), 10.0)
    acc = DepthMetricAccumulator()
    # abs_rel per image: 0.1, 0.3 (day) then 0.5 (night), 0.0 (no condition given -> 'all' only).
    two = np.concatenate([gt, gt])
    acc.update(np.concatenate([gt * 1.1, gt * 1.3]), two, conditions=["day", "day"])
    acc.update(gt * 1.5, gt, conditions="night")
    acc.update(gt, gt)
    res = acc.result()
    assert res["all"]["abs_rel"] == pytest.approx((0.1 + 0.3 + 0.5 + 0.0) / 4)
    assert res["all"]["count"] == 4
    assert res["day"]["abs_rel"] == pytest.approx(0.2) and res["day"]["count"] == 2
    assert res["night"]["abs_rel"] == pytest.approx(0.5) and res["night"]["count"] == 1
    with pytest.raises(ValueError, match="conditions"):
        acc.update(gt, gt, conditions=["day", "night"])


def test_depth_metric_errors_and_channel_axis():
    gt = np.full((2, 4, 4, 1), 5.0)
    assert depth_metrics(gt, gt)["count"] == 2
    with pytest.raises(ValueError, match="align"):
        depth_metrics(gt, gt, align="mean")
    with pytest.raises(ValueError, match="differ"):
        depth_metrics(gt[:1], gt)


def test_psnr_ssim_match_skimage():
    rng = np.random.default_rng(0)
    a = rng.random((32, 40))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    ref_ssim = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0
    )
    assert float(jax.jit(ssim)(a, b)) == pytest.approx(ref_ssim, abs=1e-5)
    ref_psnr = peak_signal_noise_ratio(a, b, data_range=1.0)
    assert float(psnr(a, b)) == pytest.approx(ref_psnr, abs=1e-3)

    a4 = rng.random((2, 24, 30, 3)) * 255
    b4 = np.clip(a4 + 25 * rng.standard_normal(a4.shape), 0, 255)
    got_ssim = np.asarray(ssim(a4, b4, data_range=255.0))
    got_psnr = np.asarray(psnr(a4, b4, data_range=255.0))
    assert got_ssim.shape == got_psnr.shape == (2,)
    for i in range(2):
        ref = structural_similarity(
            a4[i], b4[i], gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
            data_range=255.0, channel_axis=-1,
        )
        assert got_ssim[i] == pytest.approx(ref, abs=1e-5)
        assert got_psnr[i] == pytest.approx(
            peak_signal_noise_ratio(a4[i], b4[i], data_range=255.0), abs=1e-3
        )
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)


def test_entropy_hand_worked():
    halves = np.zeros((4, 4), np.uint8)
    halves[:2] = 200
    assert float(jax.jit(entropy)(halves)) == pytest.approx(1.0)
    quarters = np.array([[0, 1], [2, 3]], np.uint8)
    assert float(entropy(quarters)) == pytest.approx(2.0)
    assert float(entropy(np.zeros((3, 3), np.uint8))) == 0.0
    # p = (1/2, 1/4, 1/4): 0.5 * 1 + 2 * 0.25 * 2 = 1.5 bits.
    assert float(entropy(np.array([7, 7, 8, 9], np.uint8))) == pytest.approx(1.5)
    assert float(entropy(np.arange(256, dtype=np.uint8))) == pytest.approx(8.0)
    with pytest.raises(ValueError, match="uint8"):
        entropy(np.zeros((2, 2), np.uint16))


def test_confusion_matrix_and_miou_hand_worked():
    labels = jnp.array([[0, 0, 1], [1, 2, 255]])
    pred = jnp.array([[0, 1, 1], [1, 0, 3]])  # the ignored pixel predicts class 3
    cm = np.asarray(confusion_matrix(pred, labels, num_classes=4))
    expected = np.array([[1, 1, 0, 0], [0, 2, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(cm, expected)
    iou, present = per_class_iou(cm)
    np.testing.assert_allclose(np.asarray(iou), [1 / 3, 2 / 3, 0.0, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(present), [True, True, True, False])
    # Class 3 is absent from gt and (non-ignored) pred: left out of the mean.
    assert float(mean_iou(cm)) == pytest.approx((1 / 3 + 2 / 3 + 0.0) / 3)
    assert float(mean_iou(np.zeros((3, 3)))) == 0.0
    assert np.isfinite(np.asarray(per_class_iou(np.zeros((3, 3)))[0])).all()


def _align_case():
    """11 valid pixels: gt 2 (x5) and 4 (x6); pred 1 (x5) and 3 (x6)."""
    gt = np.array([[2.0] * 5 + [4.0] * 6 + [0.0]]).reshape(1, 3, 4)  # last pixel: no depth
    pred = np.array([[1.0] * 5 + [3.0] * 6 + [7.0]]).reshape(1, 3, 4)
    return pred, gt


@pytest.mark.parametrize("align, min_depth, abs_rel", [
    (None, 1e-3, (5 * 0.5 + 6 * 0.25) / 11),
    # median(gt) / median(pred) = 4 / 3: pred 4/3 (off by 1/3 of 2) and 4 (exact).
    ("median", 1e-3, 5 * (2 / 3) / 2 / 11),
    # The clamp comes after the alignment: 4/3 is raised to min_depth 1.5.
    ("median", 1.5, 5 * 0.5 / 2 / 11),
    # Least squares s * pred + t fits gt exactly: s = 1, t = 1.
    ("scale_shift", 1e-3, 0.0),
])
def test_alignment_and_clamp_hand_worked(align, min_depth, abs_rel):
    pred, gt = _align_case()
    m = depth_metrics(pred, gt, align=align, min_depth=min_depth)
    assert m["abs_rel"] == pytest.approx(abs_rel, abs=1e-6) and m["count"] == 1


def test_nonfinite_predictions_are_nan_and_counted_under_jit():
    gt = np.full((3, 4, 5), 10.0, np.float32)
    mask = np.ones(gt.shape, bool)
    mask[2, 0, 0] = False
    pred = gt.copy()
    pred[0] = np.nan  # all NaN: was scored d1 = 0 and silog = 0, a finite count
    pred[1, 1, 1] = np.inf  # one +inf pixel: the clamp alone would make it 80 m
    pred[2, 0, 0] = np.nan  # NaN off the mask only: the image still scores
    per = jax.jit(per_image_depth_metrics, static_argnames="align")(pred, gt, mask)
    for k in DEPTH_METRICS:
        assert np.isnan(per[k][:2]).all() and np.isfinite(per[k][2]), k
    np.testing.assert_array_equal(per["nonfinite"], [20, 1, 1])
    acc = DepthMetricAccumulator(align="median")
    acc.update(pred, gt, mask, conditions=["day", "night", "dusk"])
    res = acc.result()
    assert all(math.isnan(res[g][k]) for g in ("all", "day", "night") for k in DEPTH_METRICS)
    assert res["dusk"]["d1"] == 1.0 and res["dusk"]["abs_rel"] == pytest.approx(0.0)
    assert (res["all"]["nonfinite_pixels"], res["all"]["nonfinite_images"]) == (22, 3)
    assert (res["night"]["nonfinite_pixels"], res["night"]["nonfinite_images"]) == (1, 1)
    assert res["all"]["count"] == 3
    clean = depth_metrics(gt, gt)
    assert clean["nonfinite_pixels"] == clean["nonfinite_images"] == 0


# ----------------------------------------------------------------------------- sky metrics
def test_sky_metrics_worked_by_hand():
    """A 6x6 image whose top two rows are sky: 12 sky pixels, 5 predicted at >= 0.9 x 50 m;
    the band within 1 px of the sky is row 2, its gt 10 m, pred 12 m on half of it -> AbsRel
    (3 x 0.2 + 3 x 0) / 6 = 0.1."""
    from irdepth_jax.metrics import per_image_sky_metrics

    sky = np.zeros((1, 6, 6), bool)
    sky[0, :2] = True
    pred = np.full((1, 6, 6), 10.0, np.float32)
    pred[0, 0, :5] = 46.0  # >= 45: far
    pred[0, 1, 0] = 44.0  # not far
    pred[0, 2, :3] = 12.0
    gt = np.where(sky, 0.0, 10.0).astype(np.float32)
    out = per_image_sky_metrics(pred, gt, gt > 0, sky, 50.0, radius=1)
    np.testing.assert_allclose(out["sky_far"], [5 / 12])
    np.testing.assert_allclose(out["skyline_abs_rel"], [0.1], rtol=1e-6)
    none = per_image_sky_metrics(pred, gt, gt > 0, np.zeros_like(sky), 50.0, radius=1)
    assert np.isnan(none["sky_far"][0]) and np.isnan(none["skyline_abs_rel"][0])


def test_sky_metrics_match_a_scipy_dilation():
    """The skyline band is scipy's binary dilation of the sky by a (2r+1)^2 square, minus the
    sky; random images, radius 3."""
    from scipy import ndimage

    from irdepth_jax.metrics import per_image_sky_metrics

    rng = np.random.default_rng(0)
    sky = rng.random((3, 20, 24)) < 0.1
    gt = np.where(sky, 0.0, rng.uniform(1, 60, sky.shape)).astype(np.float32)
    mask = (gt > 0) & (rng.random(sky.shape) < 0.7)
    pred = rng.uniform(1, 90, sky.shape).astype(np.float32)
    out = per_image_sky_metrics(pred, gt, mask, sky, 70.0, radius=3)
    for b in range(3):
        band = ndimage.binary_dilation(sky[b], np.ones((7, 7), bool)) & ~sky[b] & mask[b]
        p = np.clip(pred[b], 1e-3, 80.0)
        np.testing.assert_allclose(out["skyline_abs_rel"][b],
                                   np.mean(np.abs(p[band] - gt[b][band]) / gt[b][band]), rtol=1e-5)
        np.testing.assert_allclose(out["sky_far"][b], np.mean(pred[b][sky[b]] >= 63.0), rtol=1e-6)


def test_sky_accumulator_counts_only_labelled_frames():
    from irdepth_jax.metrics import SkyMetricAccumulator

    sky = np.zeros((2, 6, 6), bool)
    sky[:, :2] = True
    gt = np.where(sky, 0.0, 10.0).astype(np.float32)
    far = np.where(sky, 80.0, 10.0).astype(np.float32)
    acc = SkyMetricAccumulator(50.0, radius=1)
    acc.update(far, gt, gt > 0, sky, np.array([True, False]), ["day", "night"])
    acc.update(np.zeros_like(far), gt, gt > 0, sky, np.array([True, True]), ["day", "day"])
    res = acc.result()
    assert res["all"]["sky_far_count"] == 3 and res["all"]["sky_far"] == pytest.approx(1 / 3)
    assert res["night"]["sky_far_count"] == 0 and np.isnan(res["night"]["sky_far"])
    assert np.isnan(acc.per_image()["sky_far"][1])
