"""Physical sanity of the procedural LWIR street renderer (small frames, a few seeds)."""

import numpy as np
import pytest

from irdepth_jax.config import CLASS_NAMES, IGNORE_LABEL
from irdepth_jax.data.synthetic import CONDITIONS, LIDAR_MAX_RANGE, render_scene
from irdepth_jax.imaging.tonemap import camera_like

H, W = 64, 80
SEEDS = range(6)
SKY, CAR, ROAD = (CLASS_NAMES.index(c) for c in ("sky", "car", "road"))


@pytest.fixture(scope="module")
def frames():
    return {c: [render_scene(s, c, H, W) for s in SEEDS] for c in CONDITIONS}


def _class_mean_raw(frames, label):
    vals = np.concatenate([f["raw14"][f["seg"] == label].astype(np.float64) for f in frames])
    assert vals.size > 0, f"no pixels of class {label}"
    return vals.mean()


def test_keys_shapes_dtypes(frames):
    f = frames["dusk"][0]
    want = dict(raw14=((H, W), np.uint16), ir8=((H, W), np.uint8), rgb=((H, W, 3), np.uint8),
                depth=((H, W), np.float32), depth_lidar=((H, W), np.float32),
                valid=((H, W), np.bool_), seg=((H, W), np.uint8))
    for k, (shape, dtype) in want.items():
        assert f[k].shape == shape and f[k].dtype == dtype, k
    assert f["condition"] == "dusk"


def test_raw_within_14_bits_and_ir8_is_camera_like(frames):
    for fs in frames.values():
        for f in fs:
            assert f["raw14"].max() <= 2**14 - 1
            assert f["raw14"].min() > 0  # no under-range clipping either
            np.testing.assert_array_equal(f["ir8"], camera_like(f["raw14"]))


def test_deterministic_per_seed():
    a, b, c = (render_scene(seed, "night", H, W) for seed in (7, 7, 8))
    for k in ("raw14", "ir8", "rgb", "depth", "depth_lidar", "valid", "seg"):
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a["raw14"], c["raw14"])
    assert not np.array_equal(a["depth"], c["depth"])


def test_road_is_the_ground_plane_and_recedes_toward_the_horizon(frames):
    f_px = 0.9 * W
    dy = -((np.arange(H) + 0.5) - 0.45 * H) / f_px  # ray slope of each row (camera looks level)
    for f in frames["day"]:
        road = f["seg"] == ROAD
        rows = np.flatnonzero(road.any(1))
        med = np.array([np.median(f["depth"][r][road[r]]) for r in rows])
        assert len(rows) > H // 4
        assert np.all(np.diff(med) < 0), "road depth must decrease toward the bottom of the image"
        cam_h = f["depth"][road] * -np.broadcast_to(dy[:, None], (H, W))[road]
        assert cam_h.min() > 1.39 and cam_h.max() < 1.61  # z = h / tan(angle below horizon)


def test_sky_has_no_depth_and_is_the_coldest_class(frames):
    for cond, fs in frames.items():
        for f in fs:
            sky = f["seg"] == SKY
            assert sky.any() and not f["valid"][sky].any() and np.all(f["depth"][sky] == 0)
            assert np.all(f["depth"][~sky] > 0)
        means = {c: _class_mean_raw(fs, c) for c in range(len(CLASS_NAMES))
                 if any((f["seg"] == c).any() for f in fs)}
        assert min(means, key=means.get) == SKY, (cond, means)


def _warmer(frames, hot, cold):
    """Per frame (each has its own gain and offset): mean raw of class hot - class cold."""
    return np.array([f["raw14"][f["seg"] == hot].mean() - f["raw14"][f["seg"] == cold].mean()
                     for f in frames if (f["seg"] == hot).any() and (f["seg"] == cold).any()])


def test_day_road_warmer_than_sky_and_night_cars_warmer_than_road(frames):
    day = _warmer(frames["day"], ROAD, SKY)
    assert len(day) == len(SEEDS) and np.all(day > 100)  # > ~2.5 K
    night = _warmer(frames["night"], CAR, ROAD)
    assert len(night) >= 4 and np.mean(night > 0) >= 0.8 and night.mean() > 20


def test_night_rgb_much_darker_than_day(frames):
    day = np.mean([f["rgb"].mean() for f in frames["day"]])
    night = np.mean([f["rgb"].mean() for f in frames["night"]])
    assert night < 0.5 * day, (day, night)


def test_lidar_is_sparse_scan_lines_within_range(frames):
    f_px = 0.9 * W
    dx = ((np.arange(W) + 0.5) - W / 2) / f_px
    dy = -((np.arange(H) + 0.5) - 0.45 * H) / f_px
    norm = np.sqrt(1 + dx[None] ** 2 + dy[:, None] ** 2)
    for f in frames["day"] + frames["night"]:
        valid, lidar, dense = f["valid"], f["depth_lidar"], f["depth"]
        np.testing.assert_array_equal(valid, lidar > 0)
        assert valid.any()
        assert not valid[f["seg"] == SKY].any()
        assert (lidar * norm)[valid].max() <= LIDAR_MAX_RANGE + 1e-3
        np.testing.assert_allclose(lidar[valid], dense[valid], rtol=0.02)
        assert valid.sum() < 0.6 * (dense > 0).sum()
        rows_hit = valid.any(1).sum()
        assert rows_hit < H * 0.75  # scan lines skip rows


def test_labels_are_known_classes(frames):
    allowed = set(range(len(CLASS_NAMES))) | {IGNORE_LABEL}
    seen = set()
    for fs in frames.values():
        for f in fs:
            seen |= set(np.unique(f["seg"]).tolist())
    assert seen <= allowed
    assert {SKY, CAR, ROAD, CLASS_NAMES.index("building")} <= seen


def test_bad_arguments():
    with pytest.raises(ValueError, match="condition"):
        render_scene(0, "noon", H, W)
    with pytest.raises(ValueError, match="height"):
        render_scene(0, "day", 4, W)
