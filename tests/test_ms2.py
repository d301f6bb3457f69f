"""MS2 adapter on a fixture built in the MS2 layout, and on a partial download of the official
split lists."""

import warnings

import cv2
import numpy as np
import pytest
from ms2_layout import official_sequences, partial_ms2

from irdepth_jax.data.folder import DatasetError, DatasetWarning
from irdepth_jax.data.ms2 import MissingSequencesError, MS2Dataset, subsample
from irdepth_jax.data.source import DataSource
from irdepth_jax.errors import RunError
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


def test_stride_subsamples_the_concatenated_split_like_the_official_loader(ms2):
    root, _ = ms2
    source = DataSource(str(root))
    ds, idx = source.frames("test", stride=5)
    # Official: sample_set[0:-1:5] over the 36 frames of the 3 test sequences, concatenated
    # (not every 5th frame of each sequence); 35, the last frame, is never picked.
    np.testing.assert_array_equal(idx, [0, 5, 10, 15, 20, 25, 30])
    day, night, rainy = LISTS["test_day"][0], LISTS["test_night"][0], LISTS["test_rainy"][0]
    assert [ds.records[i]["id"] for i in idx] == [
        f"{day}/000000", f"{day}/000005", f"{day}/000010", f"{night}/000003",
        f"{night}/000008", f"{rainy}/000001", f"{rainy}/000006"]
    # The [0:-1:N] end effect: of the 11 val frames (one lacks depth), [::10] would keep 0 and
    # 10, the official slicing keeps 0 only. Stride 1 keeps every frame.
    np.testing.assert_array_equal(source.frames("val", stride=10)[1], [0])
    np.testing.assert_array_equal(source.frames("val")[1], np.arange(N_FRAMES - 1))
    np.testing.assert_array_equal(subsample(np.arange(21), 10), [0, 10])
    with pytest.raises(ValueError, match="stride"):
        subsample(np.arange(3), 0)


def test_reader_interface(ms2):
    root, truth = ms2
    ds = MS2Dataset(root, "test_night")
    np.testing.assert_array_equal(ds.indices(), np.arange(N_FRAMES))
    np.testing.assert_array_equal(ds.indices(split="test_night"), np.arange(N_FRAMES))
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
    with pytest.raises(DatasetError, match=r"000002\.png: raw counts exceed 14 bits: "
                                           r"maximum 40000 .*data\.raw_bits=16"):
        ds[2]
    for bits in (16, "auto"):  # a 16-bit camera's counts, declared or to be detected
        assert MS2Dataset(root, "test_day", raw_bits=bits)[2]["raw14"].max() == 40000
    (root / "test_rainy_list.txt").unlink()
    with pytest.raises(DatasetError, match=r"test_rainy_list\.txt: missing split list"):
        MS2Dataset(root, "test_rainy")


def test_partial_download_of_the_official_lists(realdata, tmp_path):
    lists = realdata / "ms2_lists"
    day = official_sequences(lists, "test_day_list.txt")
    root = partial_ms2(lists, tmp_path / "ms2", present=[day[0], day[2]])
    with pytest.warns(DatasetWarning) as caught:
        ds = MS2Dataset(root, "test_day")
    assert [str(w.message) for w in caught] == [
        (f"{root}: 1 of 3 sequences of test_day_list.txt are not on disk "
         f"(no sync_data/<seq>/thr/img_left), skipped: {day[1]}")]
    assert [r["id"] for r in ds.records] == [f"{s}/{k:06d}" for s in (day[0], day[2])
                                             for k in range(3)]
    assert ds.missing == [day[1]] and ds[4]["condition"] == "day"
    with pytest.warns(DatasetWarning) as caught:
        test = MS2Dataset(root, "test")
    assert len(caught) == 1 and len(test) == 6
    assert ("7 of 9 sequences of test_day_list.txt, test_night_list.txt, test_rainy_list.txt "
            f"are not on disk (no sync_data/<seq>/thr/img_left), skipped: {day[1]}, ") in str(
                caught[0].message)
    with pytest.raises(MissingSequencesError, match=rf"1 of 3 sequences of test_day_list\.txt "
                       rf"are not on disk .*: {day[1]}$"):
        MS2Dataset(root, "test_day", strict=True)
    night = official_sequences(lists, "test_night_list.txt")
    with pytest.raises(DatasetError, match=rf"3 of 3 sequences of test_night_list\.txt are not "
                       rf"on disk .*: {', '.join(night)}$"):
        MS2Dataset(root, "test_night")


def test_data_source_warns_once_per_split_and_strict_raises(realdata, tmp_path):
    lists = realdata / "ms2_lists"
    day = official_sequences(lists, "test_day_list.txt")
    root = partial_ms2(lists, tmp_path / "ms2", present=day[:2])
    source = DataSource(str(root))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for stride in (1, 10, 1):
            assert len(source.frames("test_day", stride=stride)[1]) == (6 if stride == 1 else 1)
        assert source.frames("val", optional=True)[0] is None  # no val sequence on disk
    assert len(caught) == 1 and "1 of 3 sequences of test_day_list.txt" in str(caught[0].message)
    strict = DataSource(str(root), strict=True)
    with pytest.raises(RunError, match=rf"^`data` {root}: .*1 of 3 sequences of test_day_list"):
        strict.frames("test_day")
    with pytest.raises(RunError, match="3 of 3 sequences of val_list.txt are not on disk"):
        strict.frames("val", optional=True)  # strict: a missing sequence is never optional
