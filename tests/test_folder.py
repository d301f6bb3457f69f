"""Folder dataset format: exact round trip, clear errors, the synthetic dataset writer."""

import json

import cv2
import numpy as np
import pytest

from irdepth_jax.data.folder import DatasetError, FolderDataset, write_manifest, write_sample
from irdepth_jax.data.synthetic_dataset import (
    DEPTH_SPLIT,
    SEG_SPLIT,
    split_counts,
    synthetic_manifest,
    write_synthetic_dataset,
)


def _sample(rng, h=12, w=16, labeled=True, rgb=True):
    depth = rng.uniform(0.5, 200.0, (h, w)).astype(np.float32)
    valid = rng.random((h, w)) < 0.4
    s = dict(raw14=rng.integers(0, 2**14, (h, w)).astype(np.uint16),
             ir8=rng.integers(0, 256, (h, w)).astype(np.uint8),
             depth=np.where(valid, depth, 0), valid=valid, labeled=labeled)
    if labeled:
        s["seg"] = rng.choice([0, 1, 2, 3, 4, 5, 255], (h, w)).astype(np.uint8)
    if rgb:
        s["rgb"] = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    return s


def _write(root, samples):
    records = []
    for i, s in enumerate(samples):
        r = dict(id=f"f{i}", split="train" if i else "test",
                 seg_split="val" if s["labeled"] else None, condition="night",
                 labeled=s["labeled"])
        r.update(write_sample(root, r["id"], s))
        records.append(r)
    write_manifest(root, records, 12, 16)


def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(0)
    samples = [_sample(rng), _sample(rng, labeled=False, rgb=False)]
    _write(tmp_path, samples)
    ds = FolderDataset(tmp_path)
    assert len(ds) == 2
    for i, s in enumerate(samples):
        got = ds[i]
        np.testing.assert_array_equal(got["raw14"], s["raw14"])
        np.testing.assert_array_equal(got["ir8"], s["ir8"])
        np.testing.assert_array_equal(got["valid"], s["valid"])
        assert got["depth"].dtype == np.float32 and np.all(got["depth"][~s["valid"]] == 0)
        assert np.abs(got["depth"] - s["depth"])[s["valid"]].max() <= 1 / 512 + 1e-6
        assert got["condition"] == "night" and got["id"] == f"f{i}"
        assert got["labeled"] == s["labeled"]
    np.testing.assert_array_equal(ds[0]["seg"], samples[0]["seg"])
    np.testing.assert_array_equal(ds[0]["rgb"], samples[0]["rgb"])
    assert ds[0]["has_rgb"] and not ds[1]["has_rgb"]
    assert np.all(ds[1]["rgb"] == 0) and np.all(ds[1]["seg"] == 255)
    # the rgb PNG is a standard colour PNG: OpenCV (BGR) reads our channel order reversed
    on_disk = cv2.imread(str(tmp_path / "rgb" / "f0.png"))
    np.testing.assert_array_equal(on_disk[..., ::-1], samples[0]["rgb"])
    # depth PNG holds metres * 256
    counts = cv2.imread(str(tmp_path / "depth" / "f1.png"), cv2.IMREAD_UNCHANGED)
    assert counts.dtype == np.uint16
    want = np.where(samples[1]["valid"], np.rint(samples[1]["depth"] * 256), 0)
    np.testing.assert_array_equal(counts, want)


def test_indices_and_max_depth(tmp_path):
    rng = np.random.default_rng(1)
    samples = [_sample(rng), _sample(rng, labeled=False), _sample(rng)]
    _write(tmp_path, samples)
    ds = FolderDataset(tmp_path)
    np.testing.assert_array_equal(ds.indices(split="train"), [1, 2])
    np.testing.assert_array_equal(ds.indices(labeled=True), [0, 2])
    np.testing.assert_array_equal(ds.indices(split="train", labeled=True, seg_split="val"), [2])
    assert len(ds.indices(split="val")) == 0
    want = max(np.rint(s["depth"][s["valid"]].max() * 256) / 256 for s in samples[1:])
    assert ds.max_depth("train") == pytest.approx(want)
    for r in ds.records:  # without the manifest's per-frame max the PNGs are read: same answer
        del r["max_depth"]
    ds._max_depth.clear()
    assert ds.max_depth("train") == pytest.approx(want)
    with pytest.raises(ValueError, match="split"):
        ds.indices(split="training")


def test_missing_and_corrupt_files_name_the_path(tmp_path):
    rng = np.random.default_rng(2)
    _write(tmp_path, [_sample(rng), _sample(rng)])
    ds = FolderDataset(tmp_path)
    (tmp_path / "ir8" / "f0.png").unlink()
    with pytest.raises(DatasetError, match=r"ir8/f0\.png: missing file"):
        ds[0]
    (tmp_path / "depth" / "f1.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DatasetError, match=r"depth/f1\.png: cannot decode PNG"):
        ds[1]
    cv2.imwrite(str(tmp_path / "raw14" / "f1.png"), np.zeros((12, 16), np.uint8))
    with pytest.raises(DatasetError,
                       match=r"raw14/f1\.png: expected a 1-channel uint16 PNG, got 1-channel uint8"):
        ds[1]


def test_not_a_dataset(tmp_path):
    with pytest.raises(DatasetError, match="not a directory"):
        FolderDataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match=f"{tmp_path}: not an irdepth folder dataset"):
        FolderDataset(tmp_path)
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(DatasetError, match="manifest.json: not valid JSON"):
        FolderDataset(tmp_path)
    doc = dict(format="irdepth-folder", version=1, height=2, width=2,
               frames=[dict(id="a", split="dev")])
    (tmp_path / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="lacks"):
        FolderDataset(tmp_path)


def test_split_counts_hand_worked():
    assert split_counts(2292, DEPTH_SPLIT) == (1500, 400, 392)
    assert split_counts(800, SEG_SPLIT) == (600, 100, 100)
    assert split_counts(10, DEPTH_SPLIT) == (6, 2, 2)  # 6.54, 1.75, 1.71 -> remainders to val, test
    assert split_counts(8, SEG_SPLIT) == (6, 1, 1)


def test_synthetic_manifest_splits():
    recs = synthetic_manifest(60, 20, seed=3)
    splits = [r["split"] for r in recs]
    names = ("train", "val", "test")
    assert [splits.count(s) for s in names] == list(split_counts(60, DEPTH_SPLIT))
    lab = [r for r in recs if r["labeled"]]
    assert [sum(r["seg_split"] == s for r in lab) for s in names] == list(split_counts(20, SEG_SPLIT))
    assert all(r["seg_split"] == r["split"] for r in lab)
    assert all(r["seg_split"] is None for r in recs if not r["labeled"])
    assert [r["condition"] for r in recs[:4]] == ["day", "dusk", "night", "day"]
    assert synthetic_manifest(60, 20, seed=3) == recs and synthetic_manifest(60, 20, seed=4) != recs
    with pytest.raises(ValueError, match="labeled"):
        synthetic_manifest(5, 6, seed=0)


def test_synthetic_manifest_one_split():
    """An evaluation set: every frame in the test split, the first `labeled` of them labelled."""
    recs = synthetic_manifest(9, 4, seed=1, split="test")
    assert [r["split"] for r in recs] == ["test"] * 9
    assert sum(r["labeled"] for r in recs) == 4
    assert all(r["seg_split"] == ("test" if r["labeled"] else None) for r in recs)
    with pytest.raises(ValueError, match="split"):
        synthetic_manifest(9, 4, seed=1, split="tset")


def test_write_synthetic_dataset(tmp_path):
    out = tmp_path / "ds"
    write_synthetic_dataset(out, n=9, labeled=3, height=24, width=32, seed=5, progress=False)
    ds = FolderDataset(out, with_dense=True)
    assert len(ds) == 9 and len(ds.indices(labeled=True)) == 3
    s = ds[0]
    assert s["raw14"].shape == (24, 32) and s["has_rgb"] and s["condition"] == "day"
    assert np.all(s["depth"][s["valid"]] <= 80.0 + 1 / 512)  # stored depth: the LiDAR-like one
    assert s["valid"].sum() < (s["depth_dense"] > 0).sum()
    train_max = max(ds[i]["depth"].max() for i in ds.indices(split="train"))
    assert ds.max_depth("train") == pytest.approx(train_max)
    with pytest.raises(DatasetError, match="not empty"):
        write_synthetic_dataset(out, n=3, labeled=0, height=24, width=32, seed=0, progress=False)
    write_synthetic_dataset(out, n=3, labeled=0, height=24, width=32, seed=0, progress=False,
                            overwrite=True)
    assert len(FolderDataset(out)) == 3 and len(list((out / "raw14").iterdir())) == 3


def test_write_sample_rejects_bad_maps(tmp_path):
    rng = np.random.default_rng(3)
    s = _sample(rng)
    with pytest.raises(ValueError, match="raw14 counts must be in 0..16383"):
        write_sample(tmp_path, "a", {**s, "raw14": s["raw14"] | 0x4000})
    with pytest.raises(ValueError, match="ir8 must be uint8"):
        write_sample(tmp_path, "a", {**s, "ir8": s["ir8"].astype(np.float32)})
    with pytest.raises(ValueError, match="seg has shape"):
        write_sample(tmp_path, "a", {**s, "seg": s["seg"][:5]})
    with pytest.raises(ValueError, match="no 'seg' map"):
        write_sample(tmp_path, "a", {k: v for k, v in s.items() if k != "seg"} | {"labeled": True})
    with pytest.raises(ValueError, match="sample id"):
        write_sample(tmp_path, "../a", s)


def test_16_bit_counts(tmp_path):
    """A 16-bit camera's frames: written and read with raw_bits=16 or 'auto'; read as 14-bit
    they are an error naming the file and the setting that reads them."""
    from irdepth_jax.data.rawio import detect_raw_bits

    rng = np.random.default_rng(5)
    samples = [_sample(rng), _sample(rng, labeled=False)]
    samples[1]["raw14"] = samples[1]["raw14"] * 4 + 3  # up to 65535: over 14 bits
    with pytest.raises(ValueError, match=r"raw14 counts must be in 0\.\.16383"):
        write_sample(tmp_path, "f1", samples[1])
    records = []
    for i, s in enumerate(samples):
        r = dict(id=f"f{i}", split="train", seg_split=None, condition="day", labeled=False)
        r.update(write_sample(tmp_path, r["id"], s, raw_bits=16))
        records.append(r)
    write_manifest(tmp_path, records, 12, 16)
    with pytest.raises(DatasetError, match=r"raw14/f1\.png: raw counts exceed 14 bits: .*"
                                           r"data\.raw_bits=16"):
        FolderDataset(tmp_path)[1]
    for bits in (16, "auto"):
        np.testing.assert_array_equal(FolderDataset(tmp_path, raw_bits=bits)[1]["raw14"],
                                      samples[1]["raw14"])
    ds = FolderDataset(tmp_path, raw_bits="auto")
    assert detect_raw_bits(ds, [0, 1]) == 16
    assert detect_raw_bits(ds, [0]) == 14
    assert detect_raw_bits(ds, [0, 0, 0, 1], max_frames=2) == 16  # first and last of a sample
    with pytest.raises(ValueError, match="data.raw_bits 12"):
        FolderDataset(tmp_path, raw_bits=12)


def test_folder_keeps_no_re_export_of_the_synthetic_writer():
    """The writer's names live in one module (`data.synthetic_dataset`); `data.folder` has no
    module __getattr__ forwarding to it."""
    from irdepth_jax.data import folder

    assert not hasattr(folder, "__getattr__")
    for name in ("DEPTH_SPLIT", "SEG_SPLIT", "split_counts", "synthetic_manifest", "write_synthetic_dataset"):
        assert not hasattr(folder, name), name
