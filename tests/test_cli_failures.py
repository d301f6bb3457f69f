"""`irdepth` never reports success that did not happen: predict and train on a full disk (a
write that fails with ENOSPC, and a real tiny tmpfs where this machine lets us mount one), a
checkpoint with NaN weights, a prediction that is NaN, and a run killed with SIGKILL at random
moments that --resume continues exactly."""

import contextlib
import dataclasses
import errno
import json
import os
import random
import shutil
import subprocess
import sys
import time

import cv2
import jax
import numpy as np
import optax
import pytest
from test_cli import QUICK, one_line_error, read_metrics, run
from trained_runs import MODEL

from irdepth_jax import cli
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.fileio import mount_point
from irdepth_jax.models import pipeline
from irdepth_jax.runs import variables
from irdepth_jax.runs.checkpoint import Checkpointer, restore_model
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train import runlog
from irdepth_jax.train.state import TrainState
from irdepth_jax.train.workdir_lock import LOCK_NAME

TINY = apply_overrides(get_config("tiny"), MODEL)  # the model of the runs of QUICK
SAVE_EVERY_STEP = [*QUICK, "checkpoint_every=1"]


@pytest.fixture(scope="module")
def data(synthetic_data, stage1_run):
    """The session's shared dataset (conftest.py), test_cli's; the shared Stage I run is asked
    for first so that its train steps are in the session's compilation cache (see
    test_cli_guards.data)."""
    return synthetic_data


def train(data, work, steps=4):
    """`irdepth train stage1` of `steps` + `steps` steps, saving a checkpoint at every step."""
    return ["train", "stage1", "--data", data, "--workdir", work, "--steps", steps,
            *SAVE_EVERY_STEP]


@pytest.fixture(scope="module")
def reference(stage1_run):
    """The uninterrupted 4 + 4 step Stage I run: the session's shared `stage1_run` (conftest.py,
    read-only), the same run as `train(data, work)` but for its checkpoint interval (a
    checkpoint at the end of each phase, not at every step; checkpoints do not change what is
    trained)."""
    return stage1_run


def checkpoint_bytes(directory):
    """Disk space a checkpoint step directory takes (blocks included)."""
    return sum(max(os.stat(os.path.join(d, n)).st_blocks * 512,
                   os.path.getsize(os.path.join(d, n)))
               for d, _, names in os.walk(directory) for n in names)


@contextlib.contextmanager
def tiny_disk(path, kib):
    """A `kib` KiB tmpfs mounted at `path` (skips the test where mounting is not allowed)."""
    path.mkdir()
    mounted = os.geteuid() == 0 and shutil.which("mount") and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(path)],
        capture_output=True).returncode == 0
    if not mounted:
        pytest.skip("cannot mount a tmpfs here (needs root); the monkeypatched ENOSPC tests "
                    "cover the same code")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=True)


def error_line(err):
    return next(ln for ln in err.splitlines() if ln.startswith("irdepth: error: "))


def ends_with_one_error(code, err, *needles):
    """`one_line_error` for a run that printed what it loaded (``irdepth: stage1: ...``) first:
    exit code 2, one error line, the last one, and no traceback."""
    errors = [ln for ln in err.splitlines() if ln.startswith("irdepth: error: ")]
    assert code == 2 and errors == [err.strip().splitlines()[-1]], err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in errors[0], errors[0]


# --------------------------------------------------------------------------- predict
@pytest.fixture
def depth_model(monkeypatch):
    """predict with a stand-in Stage II model (tone-mapped input, no UNet) whose depth is noise,
    so that its PNGs do not compress: the write path without training a model."""
    cfg = dataclasses.replace(TINY, stage2=dataclasses.replace(
        TINY.stage2, preprocessing="he", sky_loss=False))
    monkeypatch.setattr(variables, "load_model",
                        lambda path, overrides=(): (cfg, "stage2", {"unet": None, "depth": {}, "warnings": []}))
    rng = np.random.default_rng(0)
    monkeypatch.setattr(pipeline, "run_pipeline", lambda unet, params, raw, cfg, image: {
        "depth": rng.uniform(1, 80, image.shape[:3]).astype(np.float32), "rgb": image,
        "hsv": None})


@pytest.fixture
def frames(tmp_path):
    """Eight raw 64x80 frames a.npy ... h.npy."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for name in "abcdefgh":
        np.save(folder / f"{name}.npy", rng.integers(3000, 9000, (64, 80)).astype(np.uint16))
    return folder


def check_outputs(out, err):
    """After a failed write: the file named in the one-line error is absent, every file there
    is a complete PNG and no temporary file is left. Returns the file names."""
    failed = error_line(err).split()[2].rstrip(":")
    assert os.path.dirname(failed) == str(out), err
    names = sorted(os.listdir(out))
    assert os.path.basename(failed) not in names and not [n for n in names if n.startswith(".")]
    for name in names:
        assert cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED) is not None, name
    return names


def test_predict_stops_at_a_write_that_fails(depth_model, frames, tmp_path, capsys,
                                             monkeypatch):
    """A disk that fills after 40 kB: the write that fails is the error, not 'wrote 16 files'."""
    budget = {"left": 40_000}
    real_write = os.write

    def write(fd, data):
        n = min(len(data), budget["left"])
        if not n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        budget["left"] -= n
        return real_write(fd, data[:n])  # the last write is short, as on a real disk

    monkeypatch.setattr(os, "write", write)
    out = tmp_path / "pred"
    code, stdout, err = run(["predict", "--checkpoint", tmp_path, "--out", out, frames], capsys)
    monkeypatch.undo()
    one_line_error(code, err, "not written: No space left on device on the disk mounted at")
    assert "wrote" not in stdout
    names = check_outputs(out, err)
    assert 0 < len(names) < 16


def test_predict_on_a_full_tmpfs(depth_model, frames, tmp_path, capsys):
    with tiny_disk(tmp_path / "disk", 64) as disk:
        out = disk / "pred"
        code, stdout, err = run(["predict", "--checkpoint", tmp_path, "--out", out, frames],
                                capsys)
        one_line_error(code, err, f"No space left on device on the disk mounted at {disk}")
        assert "wrote" not in stdout
        assert 0 < len(check_outputs(out, err)) < 16


@pytest.mark.parametrize("batch", ["1", "4"])
def test_predict_refuses_a_nan_prediction(depth_model, frames, tmp_path, capsys, monkeypatch,
                                          batch):
    """The second frame (b) predicts NaN: a's files are written, b's and the rest are not,
    whether b shares a batch with a or not."""
    seen = {"frames": 0}

    def predict(unet, params, raw, cfg, image):
        values = np.full(image.shape[:3], 5.0, np.float32)
        for i in range(len(values)):
            if seen["frames"] + i == 1:
                values[i, :2] = np.nan
        seen["frames"] += len(values)
        return {"depth": values, "rgb": image, "hsv": None}

    monkeypatch.setattr(pipeline, "run_pipeline", predict)
    out = tmp_path / "pred"
    code, _, err = run(["predict", "--checkpoint", tmp_path, "--out", out, "--batch-size", batch,
                        frames], capsys)
    one_line_error(code, err, f"{frames / 'b.npy'}: the model predicted non-finite depth "
                              "(NaN / inf) on 160 of 5120 values of frame 'b'")
    assert sorted(os.listdir(out)) == ["a_depth.png", "a_depth_color.png"]


# --------------------------------------------------------------------------- NaN weights
@pytest.fixture(scope="module")
def nan_run(reference, tmp_path_factory):
    """A copy of the reference run whose last Stage I-2 checkpoint (step 5) has three NaN
    parameters in enc0 and one inf in head_seg."""
    work = tmp_path_factory.mktemp("nan") / "w"
    shutil.copytree(reference, work)
    directory = str(work / "checkpoints" / "stage1_i2")
    model, meta = restore_model(directory, "stage1_i2", init_unet(TINY))
    params = jax.tree.map(np.array, model["params"])
    jax.tree.leaves(params["enc0"])[0].flat[:3] = np.nan
    jax.tree.leaves(params["head_seg"])[0].flat[0] = np.inf
    ckpt = Checkpointer(directory, "stage1_i2", max_to_keep=None)
    ckpt.save(5, TrainState.create(params, model["batch_stats"], optax.sgd(0.1),
                                   jax.random.PRNGKey(0)), meta, force=True)
    ckpt.wait()
    ckpt.close()
    return work


def test_nan_weights_are_refused_by_predict_and_stage2(data, nan_run, tmp_path, capsys):
    directory = nan_run / "checkpoints" / "stage1_i2"
    frame = tmp_path / "frame.npy"
    np.save(frame, np.full((32, 48), 5000, np.uint16))
    total = sum(np.size(x) for x in jax.tree.leaves(init_unet(TINY)))
    needles = [f"checkpoint {directory} step 5: 4 of {total} parameters are not finite "
               "(NaN / inf), in enc0 (3), head_seg (1)"]
    code, _, err = run(["predict", "--checkpoint", nan_run, "--out", tmp_path / "pred", frame],
                       capsys)
    one_line_error(code, err, *needles)
    assert not (tmp_path / "pred").exists()
    code, _, err = run(["train", "stage2", "--data", data, "--workdir", tmp_path / "s2",
                        "--stage1-checkpoint", nan_run, *QUICK], capsys)
    one_line_error(code, err, *needles)
    assert not (tmp_path / "s2").exists()


# --------------------------------------------------------------------------- train
def test_train_on_a_full_disk_names_the_disk_and_the_last_checkpoint(data, tmp_path, capsys,
                                                                     monkeypatch):
    """The disk fills while metrics.jsonl gets step 3 (half the line is written): one line
    naming the disk and checkpoint 2, and every finished checkpoint restores (the kill tests
    show that --resume continues exactly from such a state)."""
    real_write = runlog.RunLog.write

    def write(self, record):
        if (record["stage"], record["step"]) == ("stage1_i1", 3):
            with open(self.path, "a") as f:
                f.write(json.dumps(record)[:40])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self.path)
        real_write(self, record)

    monkeypatch.setattr(runlog.RunLog, "write", write)
    work = tmp_path / "w"
    code, _, err = run(train(data, work), capsys)
    directory = work / "checkpoints" / "stage1_i1"
    ends_with_one_error(code, err, f"no space left on the disk mounted at {mount_point(work)} (",
                   f"which holds --workdir {work}: the last good checkpoint is {directory} "
                   "step 2; free space, then continue with --resume")
    for step in (1, 2):
        restore_model(str(directory), "stage1_i1", init_unet(TINY), step=step)


@pytest.mark.parametrize("room", [0.6, 2.5])
def test_train_on_a_full_tmpfs(data, reference, tmp_path, capsys, caplog, room):
    """A tmpfs with room for 0.6 checkpoints (the first save fails in orbax's threads) or 2.5
    (one to three saves, then the disk is full: refused up front, or failing in orbax when a
    checkpoint outgrew the one before; a checkpoint's size varies with orbax's file layout,
    720-945 KB, so the room is not an exact count): one line naming the mount and the last
    finished checkpoint, no traceback, not even in the log, and every finished checkpoint
    restores."""
    size = checkpoint_bytes(reference / "checkpoints" / "stage1_i1" / "4")
    assert size > 100_000
    with tiny_disk(tmp_path / "disk", int(room * size / 1024) + 16) as disk:
        work = disk / "w"
        code, _, err = run(train(data, work), capsys)
        directory = work / "checkpoints" / "stage1_i1"
        steps = sorted(int(n) for n in os.listdir(directory) if n.isdigit())
        # room < 1: none; else a first run of steps that ends before the stage's last (4)
        assert steps == [] if room < 1 else steps in ([1], [1, 2], [1, 2, 3]), steps
        then = (f"the last good checkpoint is {directory} step {steps[-1]}" if steps
                else "no checkpoint was finished")
        ends_with_one_error(code, err, f"no space left on the disk mounted at {disk} (", then)
        assert not [r for r in caplog.records if r.exc_info], caplog.text
        for step in steps:
            restore_model(str(directory), "stage1_i1", init_unet(TINY), step=step)


def test_a_checkpoint_that_cannot_fit_is_refused_before_orbax_starts_it(tmp_path, monkeypatch):
    """Less room than the arrays (first save) or than the last checkpoint took: OSError ENOSPC
    and no step directory, not even a temporary one."""
    directory = tmp_path / "c"
    ckpt = Checkpointer(str(directory), "stage1_i1")
    state = TrainState.create({"w": np.ones(4096, np.float32)}, {}, optax.sgd(0.1),
                              jax.random.PRNGKey(0))
    usage = shutil.disk_usage(tmp_path)

    def save(step, free):
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=free))
        return ckpt.save(step, state, {})

    with pytest.raises(OSError) as refused:
        save(1, 16_000)  # the array alone takes 16384 bytes
    assert refused.value.errno == errno.ENOSPC and os.listdir(directory) == []
    assert save(1, usage.free)
    ckpt.wait()
    with pytest.raises(OSError) as refused:
        save(2, checkpoint_bytes(directory / "1") - 1)
    assert refused.value.errno == errno.ENOSPC and os.listdir(directory) == ["1"]
    assert save(2, usage.free)
    ckpt.wait()
    ckpt.close()
    assert sorted(os.listdir(directory)) == ["1", "2"]
# --------------------------------------------------------------------------- kill -9
def logged_step(work, steps, since):
    """The furthest step (counted over both phases) that metrics.jsonl shows logged at or after
    time `since` (a torn last line is skipped)."""
    furthest = 0
    with contextlib.suppress(FileNotFoundError), open(work / "metrics.jsonl") as f:
        for line in f:
            with contextlib.suppress(json.JSONDecodeError):
                r = json.loads(line)
                if r.get("kind") is None and r.get("time", 0) >= since:
                    furthest = max(furthest, r["step"] + steps * (r["stage"] == "stage1_i2"))
    return furthest


def kill_and_resume(data, work, steps, kills, seed, timeout=180):
    """Trains Stage I (`steps` + `steps`) in subprocesses, killing `kills` of them with SIGKILL
    at random moments (seeded): each once it has logged a step past the last kill's, plus 0 to
    0.5 s (in a step, a save or a log write). Each later run resumes; the last one finishes."""
    rng = random.Random(seed)
    targets = sorted(rng.sample(range(1, 2 * steps - 1), kills))
    argv = [sys.executable, "-m", "irdepth_jax.cli", *map(str, train(data, work, steps))]
    for k, target in enumerate([*targets, None]):
        started = time.time()
        with open(work.parent / f"run{k}.log", "w") as log:
            proc = subprocess.Popen(argv + ["--resume"] * (k > 0), stdout=log, stderr=log)
        try:
            while target is not None and logged_step(work, steps, started) < target:
                assert proc.poll() is None, (work.parent / f"run{k}.log").read_text()
                assert time.time() < started + timeout, f"run {k} made no progress"
                time.sleep(0.02)
            if target is not None:
                time.sleep(rng.uniform(0, 0.5))
                assert proc.poll() is None, f"run {k} finished before its kill"
                proc.kill()
            code = proc.wait(timeout=timeout)
        finally:
            proc.kill()
        assert code == (-9 if target is not None else 0), (work.parent / f"run{k}.log").read_text()


def assert_same_run(work, reference):
    assert read_metrics(work) == read_metrics(reference)
    (a, meta_a), (b, meta_b) = (restore_model(str(w / "checkpoints" / "stage1_i2"), "stage1_i2",
                                              init_unet(TINY)) for w in (work, reference))
    assert meta_a["data_state"] == meta_b["data_state"]
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert not (work / LOCK_NAME).exists()


def test_a_kill_then_resume_is_the_uninterrupted_run(data, reference, tmp_path):
    """One kill in the default suite (each restart costs a process start); ten are `slow`."""
    work = tmp_path / "w"
    kill_and_resume(data, work, steps=4, kills=1, seed=0)
    assert_same_run(work, reference)


@pytest.mark.slow
def test_ten_kills_then_resume_is_the_uninterrupted_run(data, tmp_path):
    reference = tmp_path / "reference"
    assert cli.main([str(a) for a in train(data, reference, 12)]) == 0
    work = tmp_path / "w"
    kill_and_resume(data, work, steps=12, kills=10, seed=1)
    assert_same_run(work, reference)
