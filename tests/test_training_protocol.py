"""Which frames, labels and targets each phase uses (the defects real data exposed): the
segmentation split, data without labels, the sky reference depth, brightness jitter, I-1's
frames, and resuming with a longer I-1."""

import dataclasses
import json
import os

import numpy as np
import pytest
from trained_runs import QUICK, STEPS, copy_run

from irdepth_jax import cli
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.augment import augment
from irdepth_jax.data.source import DataSource, phase_frames, stage1_i2_frames
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset
from irdepth_jax.errors import ConfigError
from irdepth_jax.evaluators import evaluate_stage1
from irdepth_jax.models.pipeline import unet_input
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.stages import sky_reference_depth

CFG = get_config("tiny")


def _rewrite_manifest(path, change):
    manifest = os.path.join(path, "manifest.json")
    with open(manifest) as f:
        doc = json.load(f)
    for r in doc["frames"]:
        change(r)
    with open(manifest, "w") as f:
        json.dump(doc, f)


@pytest.fixture(scope="module")
def independent(tmp_path_factory):
    """A dataset whose segmentation split is independent of the depth split (as the paper's
    600/100/100 split): every third labelled frame is a segmentation test frame, the others
    segmentation train frames, whatever their depth split."""
    path = tmp_path_factory.mktemp("indep") / "ds"
    write_synthetic_dataset(path, n=24, labeled=12, height=32, width=48, seed=3, progress=False)
    labelled = iter(range(100))

    def change(r):
        if r["labeled"]:
            r["seg_split"] = "test" if next(labelled) % 3 == 0 else "train"
    _rewrite_manifest(path, change)
    return path


@pytest.fixture(scope="module")
def unlabelled(tmp_path_factory):
    """A dataset without any segmentation label (as MS2)."""
    path = tmp_path_factory.mktemp("nolabels") / "ds"
    write_synthetic_dataset(path, n=16, labeled=0, height=32, width=48, seed=4, progress=False)
    return path


def _records(path):
    with open(os.path.join(path, "manifest.json")) as f:
        return json.load(f)["frames"]


# --------------------------------------------------------------------------- defect 1
def test_stage1_i2_trains_on_the_segmentation_train_split(independent):
    source = DataSource(str(independent))
    dataset, idx = phase_frames(source, "stage1_i2", CFG)
    records = _records(independent)
    assert set(idx) == {i for i, r in enumerate(records) if r["seg_split"] == "train"}
    # the old selection (labelled frames of the depth train split) holds segmentation test frames
    old = {i for i, r in enumerate(records) if r["labeled"] and r["split"] == "train"}
    assert any(records[i]["seg_split"] == "test" for i in old)


def test_miou_is_measured_on_the_segmentation_test_split(independent):
    source = DataSource(str(independent))
    dataset, test = source.frames("test")
    seg_test = source.seg_frames("test")
    want = sum(r["seg_split"] == "test" for r in _records(independent))
    result = evaluate_stage1(CFG, init_unet(CFG), dataset, test, DataParallel("single"),
                             seg_frames=seg_test)["all"]
    assert result["seg_count"] == want > 0
    assert result["count"] == len(test)
    assert not set(seg_test[1]) <= set(test)  # the old code scored the depth test frames only
    no_seg = evaluate_stage1(CFG, init_unet(CFG), dataset, test, DataParallel("single"))["all"]
    assert np.isnan(no_seg["miou"]) and no_seg["seg_count"] == 0


# --------------------------------------------------------------------------- defect 2
def test_no_labels_is_refused_before_anything_is_written(unlabelled, tmp_path, capsys):
    work = tmp_path / "run"
    code = cli.main(["train", "stage1", "--data", str(unlabelled), "--workdir", str(work),
                     "--steps", "1", *QUICK])
    err = capsys.readouterr().err
    assert code == 2 and "no segmentation labels" in err and "stage1.seg_labels=synthetic" in err
    assert not work.exists()


def test_synthetic_labels_are_mixed_with_the_unlabelled_frames(unlabelled):
    source = DataSource(str(unlabelled))
    cfg = apply_overrides(CFG, ["stage1.seg_labels=synthetic", "stage1.synthetic_labeled=5"])
    dataset, idx, info = stage1_i2_frames(source, cfg)
    train = len(source.frames("train")[1])
    assert len(idx) == train + 5 and info["labeled_frames"] == 5
    samples = [dataset[int(i)] for i in idx]
    assert sum(s["labeled"] for s in samples) == 5
    assert {np.shape(s["raw14"]) for s in samples} == {(32, 48)}
    assert all((s["seg"] != 255).any() for s in samples if s["labeled"])


# --------------------------------------------------------------------------- defect 3
def test_sky_reference_depth_is_capped_at_the_valid_range():
    cfg = CFG  # data.max_depth 80, metric head max_depth 80
    assert sky_reference_depth(cfg, 120.0) == pytest.approx(0.99 * 80.0)
    assert sky_reference_depth(cfg, 50.0) == pytest.approx(0.99 * 50.0)
    narrow = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, max_depth=20.0))
    assert sky_reference_depth(narrow, 120.0) == pytest.approx(0.99 * 20.0)


# --------------------------------------------------------------------------- defect 4
@pytest.mark.parametrize("raw_scale", ["fixed", "percentile"])
def test_brightness_is_one_change_that_survives_normalisation(raw_scale):
    s = render_scene(5, "day", 48, 64)
    sample = dict(raw14=s["raw14"], ir8=s["ir8"], rgb=s["rgb"])
    out = augment(sample, np.random.default_rng(0), p_crop=0.0, p_flip=0.0, p_brightness=1.0,
                  brightness_range=(0.8, 0.8))
    cfg = dataclasses.replace(CFG, unet=dataclasses.replace(CFG.unet, raw_scale=raw_scale))
    before = np.asarray(unet_input(out["raw14"][None], cfg))[0]
    after = np.asarray(unet_input(out["raw14"][None], cfg, out["brightness"][None]))[0]
    np.testing.assert_allclose(after, 0.8 * before, atol=1e-6)  # the model sees it ...
    target = out["ir8"].astype(float)  # ... and the 8-bit target got the same factor
    np.testing.assert_allclose(target, np.clip(np.rint(sample["ir8"] * 0.8), 0, 255))
    np.testing.assert_array_equal(out["raw14"], sample["raw14"])  # counts stay physical


# --------------------------------------------------------------------------- defect 7
def test_stage1_i1_frames_option(independent):
    source = DataSource(str(independent))
    _, train = phase_frames(source, "stage1_i1", CFG)
    assert len(train) == len(source.frames("train")[1])
    _, every = phase_frames(source, "stage1_i1", apply_overrides(CFG, ["stage1.i1_frames=all"]))
    assert len(every) == len(_records(independent)) > len(train)
    with pytest.raises(ConfigError, match=r"^stage1\.i1_frames='most': choose one of train, all$"):
        apply_overrides(CFG, ["stage1.i1_frames=most"])  # refused where the config is made


# --------------------------------------------------------------------------- defect 8
def test_resume_with_a_longer_stage1_i1_is_refused(synthetic_data, stage1_run, tmp_path,
                                                   capsys):
    """A copy of the session's shared Stage I run (--steps 4: I-2 started from I-1 step 4)."""
    work = copy_run(stage1_run, tmp_path / "run")
    base = ["train", "stage1", "--data", str(synthetic_data), "--workdir", str(work), *QUICK]
    assert STEPS["stage1"] == 4
    code = cli.main(base + ["--resume", "--steps", "8"])
    err = capsys.readouterr().err
    assert code == 2 and "started from stage1_i1 at step 4" in err and "stage1_i2" in err
    # the same length resumes as before (nothing to do)
    assert cli.main(base + ["--resume", "--steps", "4"]) == 0
