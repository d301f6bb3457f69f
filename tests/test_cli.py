"""The `irdepth` command: --help, bad-input errors, exact resume, Ctrl-C, stage2, eval, predict."""

import json
import os
import signal

import cv2
import jax
import numpy as np
import pytest

from irdepth_jax import cli
from irdepth_jax.config import get_config
from irdepth_jax.data.folder import write_synthetic_dataset
from irdepth_jax.train import loop
from irdepth_jax.train.checkpoint import Checkpointer, restore_model
from irdepth_jax.train.loop import WALL_CLOCK_FIELDS, init_unet
from irdepth_jax.train.state import TrainState

QUICK = ["--no-progress", "--devices", "1", "log_every=1", "checkpoint_every=50", "eval_every=0"]


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "ds"
    write_synthetic_dataset(path, n=24, labeled=12, height=32, width=48, seed=1, progress=False)
    return path


@pytest.fixture(scope="module")
def stage1_run(data, tmp_path_factory):
    """A straight 4 + 4 step Stage I run (used by several tests)."""
    work = tmp_path_factory.mktemp("s1") / "straight"
    assert cli.main(["train", "stage1", "--data", str(data), "--workdir", str(work),
                     "--steps", "4", *QUICK]) == 0
    return work


def read_metrics(workdir):
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    return [{k: v for k, v in r.items() if k not in WALL_CLOCK_FIELDS} for r in rows]


def final_params(workdir, phase="stage1_i2"):
    model, meta = restore_model(os.path.join(workdir, "checkpoints", phase), phase,
                                init_unet(get_config("tiny")))
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


def test_existing_workdir_is_not_overwritten(data, stage1_run, capsys):
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


def test_predict_rejects_inputs_with_the_same_name(stage1_run, tmp_path, capsys):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        np.save(tmp_path / folder / "frame.npy", np.full((32, 48), 9000, np.uint16))
    code, _, err = run(["predict", "--checkpoint", stage1_run, "--out", tmp_path / "pred",
                        tmp_path / "a", tmp_path / "b" / "frame.npy"], capsys)
    one_line_error(code, err, str(tmp_path / "b" / "frame.npy"), "same name 'frame'")
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
    real = loop.device_batch
    calls = {"n": 0}

    def interrupting(batch, phase, cfg):
        calls["n"] += 1
        if calls["n"] == 2:  # Ctrl-C while step 2 is prepared
            signal.raise_signal(signal.SIGINT)
        return real(batch, phase, cfg)

    monkeypatch.setattr(loop, "device_batch", interrupting)
    work = tmp_path / "ctrl_c"
    args = ["train", "stage1", "--data", data, "--workdir", work, "--steps", "4", *QUICK]
    code, _, err = run(args, capsys)
    assert code == 130 and "interrupted" in err, err
    reader = Checkpointer(str(work / "checkpoints" / "stage1_i1"), "stage1_i1")
    assert reader.latest_step() == 2
    reader.close()
    monkeypatch.setattr(loop, "device_batch", real)
    code, _, err = run(args + ["--resume"], capsys)
    assert code == 0, err
    assert read_metrics(work) == read_metrics(stage1_run)


# --------------------------------------------------------------------------- stage 2 + tools
def test_stage2_eval_and_predict(data, stage1_run, tmp_path, capsys):
    work = tmp_path / "s2"
    code, out, err = run(["train", "stage2", "--data", data, "--workdir", work, "--steps", "2",
                          "--stage1-checkpoint", stage1_run, *QUICK], capsys)
    assert code == 0, err
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

    raw = np.asarray(loop.DataSource(str(data)).frames("test")[0][0]["raw14"])
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
    """A directory with MS2's layout trains without --format (no labels: I-2 sees only 255)."""
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
    code, out, err = run(["train", "stage1", "--data", root, "--workdir", work, "--steps", "1",
                          *QUICK], capsys)
    assert code == 0, err
    rows = read_metrics(work)
    assert [r["stage"] for r in rows] == ["stage1_i1", "stage1_i2"]
    assert rows[1]["ce"] == 0.0 and np.isfinite(rows[1]["loss"])
    # the MS2 evaluation protocol: every N-th frame of each sequence
    for stride, count in ((1, 4), (2, 2), (3, 2)):
        code, out, err = run(["eval", "--workdir", work, "--data", root, "--split", "val",
                              "--stride", str(stride), "--out", tmp_path / f"e{stride}"], capsys)
        assert code == 0, err
        with open(tmp_path / f"e{stride}" / "eval_val.json") as f:
            assert json.load(f)["stage1"]["all"]["count"] == count
