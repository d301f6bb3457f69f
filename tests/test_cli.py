"""The `irdepth` command: --help, bad-input errors, exact resume, Ctrl-C, stage2, eval, predict."""

import json
import os
import signal

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trained_runs
from da_params import random_params
from ms2_layout import official_sequences, partial_ms2

from irdepth_jax import cli, evaluators
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.source import DataSource
from irdepth_jax.models.depth_anything import depth_anything_config
from irdepth_jax.runs.checkpoint import Checkpointer, restore_model
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train import phase, runlog
from irdepth_jax.train.runlog import WALL_CLOCK_FIELDS
from irdepth_jax.train.state import TrainState
from irdepth_jax.weights import to_official_state_dict

QUICK = trained_runs.QUICK  # also imported by test_cli_guards and test_cli_failures


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def data(synthetic_data):
    """The session's shared dataset (conftest.py); `stage1_run` (a straight 4 + 4 step Stage I
    run) and `stage2_run` are the session's shared runs on it, read-only."""
    return synthetic_data


def read_metrics(workdir):
    """The step and eval records of metrics.jsonl, without wall-clock fields or info records."""
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    return [{k: v for k, v in r.items() if k not in WALL_CLOCK_FIELDS} for r in rows
            if r.get("kind") != "info"]


def final_params(workdir, phase="stage1_i2", overrides=tuple(trained_runs.MODEL)):
    """(model variables, meta) of the last checkpoint of `phase` in a run of the tiny preset
    with `overrides` (default: the CLI tests' model, `trained_runs.MODEL`)."""
    model, meta = restore_model(os.path.join(workdir, "checkpoints", phase), phase,
                                init_unet(apply_overrides(get_config("tiny"), list(overrides))))
    return model, meta


# --------------------------------------------------------------------------- help
@pytest.mark.parametrize("command", [[], ["synth"], ["train"], ["eval"], ["predict"],
                                     ["quickstart"]])
def test_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(command + ["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: irdepth" in out
    if command:
        assert len(out.splitlines()) > 5


# --------------------------------------------------------------------------- bad input
def one_line_error(code, err, *needles):
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("irdepth")]
    assert len(lines) == 1 and lines[0].startswith("irdepth: error: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_unknown_config_key(data, tmp_path, capsys):
    work = tmp_path / "w"
    code, _, err = run(["train", "stage1", "--data", data, "--workdir", work, "unet.nope=1"],
                       capsys)
    one_line_error(code, err, "unet.nope")
    assert not work.exists()
    bad_json = tmp_path / "c.json"
    bad_json.write_text(json.dumps({"stage1": {"w_rec": 0.2, "bogus": 1}}))
    code, _, err = run(["train", "stage1", "--data", data, "--workdir", work, "--config",
                        bad_json], capsys)
    one_line_error(code, err, "stage1.bogus")


def test_config_files(tmp_path):
    good_json = tmp_path / "c.json"
    good_json.write_text(json.dumps({"stage1": {"w_rec": 0.2}, "seed": 4}))
    cfg = cli.load_config("tiny", str(good_json), ["stage1.w_seg=2"])
    assert (cfg.stage1.w_rec, cfg.stage1.w_seg, cfg.seed, cfg.name) == (0.2, 2.0, 4, "tiny")
    py = tmp_path / "c.py"
    py.write_text("from irdepth_jax.config import get_config as g\n"
                  "def get_config():\n    return g('small')\n")
    assert cli.load_config("tiny", str(py), []).name == "small"


def test_not_a_dataset(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = run(["train", "stage1", "--data", tmp_path / "empty", "--workdir",
                        tmp_path / "w"], capsys)
    one_line_error(code, err, str(tmp_path / "empty"), "manifest")
    assert not (tmp_path / "w").exists()
    code, _, err = run(["eval", "--workdir", tmp_path / "nothing", "--data", tmp_path / "empty"],
                       capsys)
    one_line_error(code, err, str(tmp_path / "nothing"))


def test_existing_workdir_is_not_overwritten(data, stage1_run, tmp_path, capsys):
    stage1_run = trained_runs.copy_run(stage1_run, tmp_path / "straight")
    before = (stage1_run / "config.json").read_text()
    metrics = (stage1_run / "metrics.jsonl").read_text()
    code, _, err = run(["train", "stage1", "--data", data, "--workdir", stage1_run, "--steps",
                        "2", "--no-progress", "seed=5"], capsys)
    one_line_error(code, err, str(stage1_run), "--resume")
    assert (stage1_run / "config.json").read_text() == before
    assert (stage1_run / "metrics.jsonl").read_text() == metrics
    # --resume with a changed hyper-parameter is refused too
    code, _, err = run(["train", "stage1", "--data", data, "--workdir", stage1_run, "--steps",
                        "4", "--resume", *QUICK, "seed=5"], capsys)
    one_line_error(code, err, "seed")


def test_checkpoint_of_wrong_stage_or_shape(data, stage1_run, tmp_path, capsys):
    fake = tmp_path / "fake_stage2"
    ckpt = Checkpointer(str(fake), "stage2")
    import optax
    ckpt.save(1, TrainState.create({"w": np.ones(3, np.float32)}, {}, optax.sgd(0.1),
                                   jax.random.PRNGKey(0)), {})
    ckpt.wait()
    ckpt.close()
    code, _, err = run(["train", "stage2", "--data", data, "--workdir", tmp_path / "w2",
                        "--stage1-checkpoint", fake, "--no-progress"], capsys)
    one_line_error(code, err, str(fake), "'stage2' checkpoint", "stage1_i2")
    assert not (tmp_path / "w2").exists()
    code, _, err = run(["eval", "--workdir", stage1_run, "--data", data, "--out", tmp_path / "e",
                        "unet.widths=(8, 8, 8, 8)"], capsys)
    one_line_error(code, err, "stage1_i2", "has shape")
    assert not (tmp_path / "e").exists()


def test_predict_rejects_8bit_files(stage1_run, tmp_path, capsys):
    img8 = tmp_path / "frame8.png"
    cv2.imwrite(str(img8), np.full((32, 48), 100, np.uint8))
    code, _, err = run(["predict", "--checkpoint", stage1_run, "--out", tmp_path / "pred",
                        img8], capsys)
    one_line_error(code, err, str(img8), "8-bit")
    assert not (tmp_path / "pred").exists()
    over = tmp_path / "over14.npy"
    np.save(over, np.full((32, 48), 20000, np.uint16))
    code, _, err = run(["predict", "--checkpoint", stage1_run, "--out", tmp_path / "pred", over],
                       capsys)
    one_line_error(code, err, str(over))
    assert not (tmp_path / "pred").exists()


def test_predict_rejects_frames_of_the_same_name_in_one_folder(stage1_run, tmp_path, capsys):
    """(Same-named frames of different inputs go to sub-folders: tests/test_predict_folders.py.)"""
    np.save(tmp_path / "frame.npy", np.full((32, 48), 9000, np.uint16))
    cv2.imwrite(str(tmp_path / "frame.png"), np.full((32, 48), 9000, np.uint16))
    code, _, err = run(["predict", "--checkpoint", stage1_run, "--out", tmp_path / "pred",
                        tmp_path], capsys)
    one_line_error(code, err, str(tmp_path / "frame.png"), "same name 'frame'")
    assert not (tmp_path / "pred").exists()


# --------------------------------------------------------------------------- resume
def test_resume_continues_exactly(data, stage1_run, tmp_path, capsys):
    work = tmp_path / "split"
    args = ["train", "stage1", "--data", data, "--workdir", work, "--steps", "4", *QUICK]
    code, _, err = run(args + ["--stop-at", "3"], capsys)
    assert code == 130 and "step 3" in err and "--resume" in err
    code, _, err = run(args + ["--resume"], capsys)
    assert code == 0, err
    straight_rows, split_rows = read_metrics(stage1_run), read_metrics(work)
    assert [(r["stage"], r["step"]) for r in straight_rows] == [
        ("stage1_i1", s) for s in range(1, 5)] + [("stage1_i2", s) for s in range(1, 5)]
    assert split_rows == straight_rows
    (a, meta_a), (b, meta_b) = final_params(stage1_run), final_params(work)
    assert meta_a["data_state"] == meta_b["data_state"]
    jax.tree.map(np.testing.assert_array_equal, a, b)


def test_ctrl_c_saves_a_checkpoint(data, stage1_run, tmp_path, capsys, monkeypatch):
    real = phase.device_batch
    calls = {"n": 0}

    def interrupting(batch, phase, cfg):
        calls["n"] += 1
        if calls["n"] == 2:  # Ctrl-C while step 2 is prepared
            signal.raise_signal(signal.SIGINT)
        return real(batch, phase, cfg)

    monkeypatch.setattr(phase, "device_batch", interrupting)
    work = tmp_path / "ctrl_c"
    args = ["train", "stage1", "--data", data, "--workdir", work, "--steps", "4", *QUICK]
    code, _, err = run(args, capsys)
    assert code == 130 and "interrupted" in err, err
    reader = Checkpointer(str(work / "checkpoints" / "stage1_i1"), "stage1_i1")
    assert reader.latest_step() == 2
    reader.close()
    monkeypatch.setattr(phase, "device_batch", real)
    code, _, err = run(args + ["--resume"], capsys)
    assert code == 0, err
    assert read_metrics(work) == read_metrics(stage1_run)


# --------------------------------------------------------------------------- stage 2 + tools
def test_stage2_eval_and_predict(data, stage2_run, tmp_path, capsys, monkeypatch):
    """The shared Stage II run (2 steps from `stage1_run`), evaluated into a copy of it."""
    work = trained_runs.copy_run(stage2_run, tmp_path / "s2")
    rows = read_metrics(work)
    assert [r["step"] for r in rows] == [1, 2]
    assert {"silog", "sky", "loss", "lr_backbone", "lr_head"} <= set(rows[0])
    assert rows[0]["lr_head"] == pytest.approx(10 * rows[0]["lr_backbone"])
    assert any(name.startswith("events") for name in os.listdir(work / "tb"))

    code, out, err = run(["eval", "--workdir", work, "--data", data, "--split", "test"], capsys)
    assert code == 0, err
    table = json.loads((work / "eval_test.json").read_text())
    assert {"d1", "abs_rel", "rmse", "silog"} <= set(table["stage2"]["all"])
    assert {"psnr", "ssim", "entropy", "miou"} <= set(table["stage1"]["all"])
    assert "| all |" in (work / "eval_test.md").read_text() and "abs_rel" in out
    test_frames = len(DataSource(str(data)).frames("test")[1])
    labels = {"depth": "metric", "reconstruction": "the dataset's 8-bit camera image (ir8)",
              "ground_truth": "the folder dataset's depth/"}
    assert table["protocol"] == {"stride": 1, "frames": test_frames, "align": "none",
                                 "clamp": [1e-3, 80.0], **labels}
    assert table["stage2"]["all"]["nonfinite_images"] == 0 and "WARNING" not in err

    # A model predicting NaN is reported loudly, not scored (d1 = 0, silog = 0 before).
    monkeypatch.setitem(evaluators._PREDICT, "stage2",
                        lambda cfg, variables, batch: {"depth": jnp.full(batch["raw14"].shape,
                                                                         jnp.nan)})
    evaluators._eval_step.cache_clear()
    try:
        code, out, err = run(["eval", "--workdir", work, "--data", data, "--split", "test",
                              "--align", "median", "--stride", "2", "--out", tmp_path / "nan"],
                             capsys)
    finally:
        evaluators._eval_step.cache_clear()
    assert code == 0, err
    nan = json.loads((tmp_path / "nan" / "eval_test.json").read_text())
    frames = len(range(test_frames)[0:-1:2])
    assert nan["protocol"] == {"stride": 2, "frames": frames, "align": "median",
                               "clamp": [1e-3, 80.0], **labels}
    assert nan["stage2"]["all"]["nonfinite_images"] == frames
    assert np.isnan(nan["stage2"]["all"]["d1"]) and np.isnan(nan["stage2"]["all"]["silog"])
    assert [ln for ln in err.splitlines() if "non-finite" in ln] == [
        ("irdepth: WARNING: the model predicted non-finite depth (NaN / inf) on "
         f"{nan['stage2']['all']['nonfinite_pixels']} pixels of {frames} of {frames} images; "
         "their metrics are NaN")]

    raw = np.asarray(DataSource(str(data)).frames("test")[0][0]["raw14"])
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "a.png"), raw)
    np.save(frames / "b.npy", raw)
    code, out, err = run(["predict", "--checkpoint", work, "--out", tmp_path / "pred", frames],
                         capsys)
    assert code == 0, err
    names = sorted(os.listdir(tmp_path / "pred"))
    assert names == sorted(f"{s}_{k}.png" for s in "ab"
                           for k in ("depth", "depth_color", "rgb", "hsv"))
    depth = cv2.imread(str(tmp_path / "pred" / "a_depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == raw.shape and depth.max() > 0
    same = cv2.imread(str(tmp_path / "pred" / "b_depth.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(depth, same)


def test_synth(tmp_path, capsys):
    code, out, _ = run(["synth", "--out", tmp_path / "d", "--n", "6", "--labeled", "3",
                        "--size", "16x24", "--no-progress"], capsys)
    assert code == 0 and "6 frames" in out
    manifest = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert (manifest["height"], manifest["width"], len(manifest["frames"])) == (16, 24, 6)
    code, _, err = run(["synth", "--out", tmp_path / "d", "--n", "6", "--no-progress"], capsys)
    one_line_error(code, err, str(tmp_path / "d"))


def test_ms2_layout_is_detected(tmp_path, capsys):
    """A directory with MS2's layout trains without --format; it has no labels, so I-2 mixes in
    rendered labelled scenes (stage1.seg_labels=synthetic) and its cross-entropy is not 0."""
    root = tmp_path / "ms2"
    rng = np.random.default_rng(0)
    for split, seq in (("train", "_seq_a"), ("val", "_seq_b")):
        (root / f"{split}_list.txt").parent.mkdir(parents=True, exist_ok=True)
        (root / f"{split}_list.txt").write_text(seq + "\n")
        img_dir = root / "sync_data" / seq / "thr" / "img_left"
        depth_dir = root / "proj_depth" / seq / "thr" / "depth_filtered"
        img_dir.mkdir(parents=True)
        depth_dir.mkdir(parents=True)
        for k in range(4):
            cv2.imwrite(str(img_dir / f"{k:06d}.png"),
                        rng.integers(3000, 6000, (32, 48)).astype(np.uint16))
            cv2.imwrite(str(depth_dir / f"{k:06d}.png"),
                        rng.integers(0, 30 * 256, (32, 48)).astype(np.uint16))
    work = tmp_path / "w"
    code, out, err = run(["train", "stage1", "--data", root, "--workdir", work, "--steps", "2",
                          *QUICK, "stage1.seg_labels=synthetic", "stage1.synthetic_labeled=8"],
                         capsys)
    assert code == 0, err
    assert "'synthetic': 8" in err  # says where the labels came from
    rows = read_metrics(work)
    assert [r["stage"] for r in rows] == ["stage1_i1"] * 2 + ["stage1_i2"] * 2
    assert sum(r["ce"] for r in rows[2:]) > 0 and np.isfinite(rows[-1]["loss"])
    # the MS2 evaluation protocol: frames[0:-1:N] of the split (every frame for N = 1)
    for stride, count in ((1, 4), (2, 2), (3, 1)):
        code, out, err = run(["eval", "--workdir", work, "--data", root, "--split", "val",
                              "--stride", str(stride), "--out", tmp_path / f"e{stride}"], capsys)
        assert code == 0, err
        with open(tmp_path / f"e{stride}" / "eval_val.json") as f:
            result = json.load(f)
        assert result["stage1"]["all"]["count"] == result["protocol"]["frames"] == count
        assert result["protocol"]["stride"] == stride


def test_partial_ms2_download_warns_once_and_strict_fails(stage1_run, realdata, tmp_path,
                                                         capsys):
    lists = realdata / "ms2_lists"
    day = official_sequences(lists, "test_day_list.txt")
    train = official_sequences(lists, "train_list.txt")
    root = partial_ms2(lists, tmp_path / "ms2", present=[day[0], day[2], train[0]],
                       size=(32, 48))
    missing = "1 of 3 sequences of test_day_list.txt are not on disk"
    code, _, err = run(["eval", "--workdir", stage1_run, "--data", root, "--split",
                        "test_day", "--strict", "--out", tmp_path / "e"], capsys)
    one_line_error(code, err, missing, day[1])
    code, _, err = run(["train", "stage1", "--data", root, "--workdir", tmp_path / "w",
                        "--strict", *QUICK, "stage1.seg_labels=none"], capsys)
    one_line_error(code, err, f"{len(train) - 1} of {len(train)} sequences of train_list.txt",
                   train[-1])
    code, _, err = run(["eval", "--workdir", stage1_run, "--data", root, "--split",
                        "test_day", "--stride", "2", "--out", tmp_path / "e"], capsys)
    assert code == 0, err
    assert [ln for ln in err.splitlines() if "not on disk" in ln] == [
        (f"irdepth: warning: {root}: {missing} (no sync_data/<seq>/thr/img_left), "
         f"skipped: {day[1]}")], err
    assert "DatasetWarning" not in err and "warnings.warn" not in err
    result = json.loads((tmp_path / "e" / "eval_test_day.json").read_text())
    assert result["protocol"]["frames"] == 3 and result["stage1"]["all"]["count"] == 3


# --------------------------------------------------------------------------- set-up errors
BASELINE = ["stage2.preprocessing=he", "stage2.sky_loss=false"]  # Stage II without Stage I


def test_stage2_says_what_it_loaded_from_a_released_checkpoint(data, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    params = random_params(depth_anything_config("tiny"), seed=2)
    ckpt = tmp_path / "depth_anything_v2_metric_hypersim_vits.pth"  # an official metric name
    torch.save({k: torch.from_numpy(v) for k, v in to_official_state_dict(params).items()}, ckpt)
    work = tmp_path / "s2"
    # as long as the depth pretraining runs of test_depth_pretraining: the same compiled step
    # (an image fed from the host, the same decay schedule)
    args = ["train", "stage2", "--data", data, "--steps", "2", *QUICK, *BASELINE,
            f"depth.checkpoint={ckpt}"]
    code, _, err = run(args + ["--workdir", work], capsys)
    assert code == 0, err
    said = {"backbone": f"loaded from {ckpt} (encoder tiny)",
            "head": f"loaded from {ckpt} (metric, max_depth 20 m)",
            "max_depth": "warning: the head was trained for max_depth 20 m; depth.max_depth=80 "
                         "scales its output by 4"}
    for key, value in said.items():
        assert f"irdepth: stage2: {key}: {value}" in err.splitlines()
    assert {"step": 0, "stage": "stage2", "kind": "info", **said} in runlog.read_metrics(
        os.path.join(work, "metrics.jsonl"))
    ckpt.unlink()  # the run's own checkpoint is all its evaluation needs
    code, _, err = run(["eval", "--workdir", work, "--data", data, "--split", "test"], capsys)
    assert code == 0, err
    code, _, err = run(args + ["--workdir", tmp_path / "again"], capsys)
    one_line_error(code, err, "depth.checkpoint", f"no checkpoint at '{ckpt}'")
    assert not (tmp_path / "again").exists()


@pytest.mark.parametrize("argv, message", [
    (["stage1", "stage1.batch_size=1", "stage1.accum_steps=4"],
     "stage1.batch_size=1 is not a multiple of stage1.accum_steps=4 x 1 device: set "
     "stage1.accum_steps=1 or stage1.batch_size=4"),
    (["stage1", "stage1.batch_size=6", "stage1.accum_steps=4", "--devices", "2"],
     "stage1.batch_size=6 is not a multiple of stage1.accum_steps=4 x 2 devices: set "
     "stage1.accum_steps=3 or stage1.batch_size=8"),
    (["stage2", *BASELINE, "stage2.batch_size=6", "--devices", "4"],
     "stage2.batch_size=6 is not a multiple of 4 devices: set --devices 3 or "
     "stage2.batch_size=8"),
    (["stage1", "stage1.batch_size=64", "stage1.accum_steps=1"],
     "stage1.batch_size=64 is larger than the 16 training frames of stage1_i1 (an epoch drops "
     "its incomplete last batch, so it would have no step): set stage1.batch_size=16"),
    (["stage1", "stage1.batch_size=12", "stage1.accum_steps=4"],  # 9 labelled: before I-1 runs
     "stage1.batch_size=12 is larger than the 9 training frames of stage1_i2 (an epoch drops "
     "its incomplete last batch, so it would have no step): set stage1.batch_size=8"),
    (["stage2", *BASELINE, "stage2.batch_size=18"],
     "stage2.batch_size=18 is larger than the 16 training frames of stage2"),
])
def test_batch_that_cannot_be_split_is_refused_before_the_run(data, tmp_path, capsys, argv,
                                                              message):
    work = tmp_path / "w"
    code, _, err = run(["train", *argv[:1], "--data", data, "--workdir", work, "--no-progress",
                        *argv[1:]], capsys)
    one_line_error(code, err, message)
    assert not work.exists()
