"""MS2 adapter on a fixture built in the MS2 layout."""

import cv2
import numpy as np
import pytest

from irdepth_jax.data.folder import DatasetError
from irdepth_jax.data.ms2 import MS2Dataset
from irdepth_jax.imaging.tonemap import camera_like

LISTS = {"train": ["_2021-08-06-10-59-33", "_2021-08-13-22-16-02"], "val": ["_2021-08-06-16-19-00"],
         "test_day": ["_2021-08-06-11-37-46"], "test_night": ["_2021-08-13-21-58-13"],
         "test_rainy": ["_2021-08-06-17-44-55"]}
N_FRAMES, H, W = 12, 16, 20


@pytest.fixture
def ms2(tmp_path):
    rng = np.random.default_rng(0)
    truth = {}
    for split, seqs in LISTS.items():
        (tmp_path / f"{split}_list.txt").write_text("".join(s + "\n" for s in seqs) + "\n")
        for seq in seqs:
            img_dir = tmp_path / "sync_data" / seq / "thr" / "img_left"
            dep_dir = tmp_path / "proj_depth" / seq / "thr" / "depth_filtered"
            img_dir.mkdir(parents=True)
            dep_dir.mkdir(parents=True)
            for k in range(N_FRAMES):
                name = f"{k:06d}.png"
                raw = rng.integers(3000, 6000, (H, W)).astype(np.uint16)
                dep = np.where(rng.random((H, W)) < 0.3, rng.integers(1, 80 * 256, (H, W)), 0)
                dep = dep.astype(np.uint16)
                cv2.imwrite(str(img_dir / name), raw)
                if not (seq == LISTS["val"][0] and k == 3):  # one frame without depth
                    cv2.imwrite(str(dep_dir / name), dep)
                truth[f"{seq}/{k:06d}"] = (raw, dep)
    return tmp_path, truth


def test_reads_frames_with_conditions_from_list_files(ms2):
    root, truth = ms2
    for split, cond in (("test_day", "day"), ("test_night", "night"), ("test_rainy", "rainy")):
        ds = MS2Dataset(root, split)
        assert len(ds) == N_FRAMES
        s = ds[5]
        raw, dep = truth[s["id"]]
        assert s["id"] == f"{LISTS[split][0]}/000005" and s["condition"] == cond
        np.testing.assert_array_equal(s["raw14"], raw)
        np.testing.assert_array_equal(s["depth"], dep.astype(np.float32) / 256)
        np.testing.assert_array_equal(s["valid"], dep > 0)
        np.testing.assert_array_equal(s["ir8"], camera_like(raw))
        assert s["rgb"].shape == (H, W, 3) and not s["rgb"].any() and not s["has_rgb"]
        assert np.all(s["seg"] == 255) and not s["labeled"]
    test = MS2Dataset(root, "test")
    assert [r["condition"] for r in test.records[::N_FRAMES]] == ["day", "night", "rainy"]


def test_train_val_conditions_and_missing_depth(ms2):
    root, _ = ms2
    train = MS2Dataset(root, "train")
    assert len(train) == 2 * N_FRAMES and {r["condition"] for r in train.records} == {"unknown"}
    train = MS2Dataset(root, "train", conditions={LISTS["train"][1]: "night"})
    assert train[N_FRAMES]["condition"] == "night" and train[0]["condition"] == "unknown"
    val = MS2Dataset(root, "val")
    assert len(val) == N_FRAMES - 1 and val.skipped == 1
    assert "000003" not in {r["id"].split("/")[1] for r in val.records}


def test_stride_protocol_and_reader_interface(ms2):
    root, truth = ms2
    ds = MS2Dataset(root, "test_night", stride=10)
    assert [r["id"].split("/")[1] for r in ds.records] == ["000000", "000010"]
    np.testing.assert_array_equal(ds.indices(), [0, 1])
    np.testing.assert_array_equal(ds.indices(split="test_night"), [0, 1])
    assert len(ds.indices(labeled=True)) == 0
    want = max(truth[r["id"]][1].max() for r in ds.records) / 256
    assert ds.max_depth() == pytest.approx(want)
    with pytest.raises(ValueError, match="holds split"):
        ds.indices(split="train")


def test_errors_name_the_file(ms2, tmp_path_factory):
    root, _ = ms2
    with pytest.raises(ValueError, match="split must be"):
        MS2Dataset(root, "testing")
    with pytest.raises(DatasetError, match="not an MS2 root"):
        MS2Dataset(tmp_path_factory.mktemp("empty"), "train")
    seq = LISTS["test_day"][0]
    bad = root / "sync_data" / seq / "thr" / "img_left" / "000002.png"
    cv2.imwrite(str(bad), np.full((H, W), 40000, np.uint16))
    ds = MS2Dataset(root, "test_day")
    with pytest.raises(DatasetError, match=r"000002\.png: counts up to 40000, over 14 bits"):
        ds[2]
    (root / "test_rainy_list.txt").unlink()
    with pytest.raises(DatasetError, match=r"test_rainy_list\.txt: missing split list"):
        MS2Dataset(root, "test_rainy")
