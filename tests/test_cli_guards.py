"""`irdepth train` never reports success that did not happen: nonsense run lengths and rates,
--resume without a run, data without depth, broken config files, torn metrics lines, a second
Ctrl-C, a run that fails before its first step, and two runs on one workdir (the lock)."""

import json
import os
import signal
import socket
import subprocess
import sys

import cv2
import numpy as np
import orbax.checkpoint as ocp
import pytest
from test_cli import QUICK, one_line_error, read_metrics, run

from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset
from irdepth_jax.errors import RunError
from irdepth_jax.runs import checkpoint
from irdepth_jax.train import phase, stages
from irdepth_jax.train.workdir_lock import LOCK_NAME


@pytest.fixture(scope="module")
def data(synthetic_data, stage1_run):
    """The session's shared dataset (conftest.py), test_cli's. Asking for the shared Stage I
    run too means its train steps are in the session's compilation cache before the tests here
    train on the same data (one compile instead of two)."""
    return synthetic_data


def train(data, work, *extra):
    return ["train", "stage1", "--data", data, "--workdir", work, *QUICK, *extra]


# --------------------------------------------------------------------------- refused up front
@pytest.mark.parametrize("extra, needle", [
    (["--steps", "0"], "--steps 0"),
    (["--steps", "-3"], "--steps -3"),
    (["--stop-at", "0"], "--stop-at 0"),
    (["stage1.steps_i1=2.5"], "'stage1.steps_i1' expects an integer (or none)"),
    (["stage1.steps_i1=abc"], "'stage1.steps_i1' expects an integer (or none)"),
    (["stage1.epochs_i2=0"], "stage1.epochs_i2=0"),
    (["stage1.batch_size=0"], "stage1.batch_size=0"),
    (["stage1.accum_steps=-1"], "stage1.accum_steps=-1"),
    (["stage1.steps_i1=0", "stage1.steps_i2=0"], "would train nothing"),
    (["log_every=0"], "log_every=0"),
    (["stage1.learning_rate=nan"], "stage1.learning_rate=nan"),
    (["stage1.i2_learning_rate=0"], "stage1.i2_learning_rate=0"),
    (["stage1.seg_lr_multiplier=-1"], "stage1.seg_lr_multiplier=-1"),
    (["--resume"], "holds no run"),
])
def test_stage1_refused_before_anything_is_made(data, tmp_path, capsys, extra, needle):
    work = tmp_path / "w"
    code, _, err = run(train(data, work, *extra), capsys)
    one_line_error(code, err, needle)
    assert not work.exists()


@pytest.mark.parametrize("extra, needle", [
    (["stage2.learning_rate=inf"], "stage2.learning_rate=inf"),
    (["stage2.head_lr_multiplier=0"], "stage2.head_lr_multiplier=0"),
    (["stage2.steps=0"], "stage2.steps=0"),
    (["stage2.epochs=0"], "stage2.epochs=0"),
])
def test_stage2_refused_before_anything_is_made(data, tmp_path, capsys, extra, needle):
    work = tmp_path / "w"
    code, _, err = run(["train", "stage2", "--data", data, "--workdir", work, *QUICK, *extra],
                       capsys)
    one_line_error(code, err, needle)
    assert not work.exists()


def test_config_file_values_are_checked(data, tmp_path, capsys):
    config = tmp_path / "c.json"
    config.write_text(json.dumps({"stage1": {"steps_i1": 2.5}}))
    code, _, err = run(train(data, tmp_path / "w", "--config", config), capsys)
    one_line_error(code, err, "stage1.steps_i1=2.5")


def test_resume_on_an_empty_directory(data, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = run(train(data, tmp_path / "empty", "--resume"), capsys)
    one_line_error(code, err, "holds no run", "--resume-or-start")
    assert os.listdir(tmp_path / "empty") == []


def test_stage2_resume_of_a_stage1_workdir(data, tmp_path, capsys):
    work = tmp_path / "s1"
    (work / "checkpoints" / "stage1_i2" / "4").mkdir(parents=True)
    (work / "config.json").write_text("{}")
    code, _, err = run(["train", "stage2", "--data", data, "--workdir", work, "--resume",
                        *QUICK], capsys)
    one_line_error(code, err, "holds a stage1 run")
    assert sorted(os.listdir(work)) == ["checkpoints", "config.json"]
    assert os.listdir(work / "checkpoints") == ["stage1_i2"]


def test_stage2_without_valid_depth(tmp_path, capsys):
    root = write_synthetic_dataset(tmp_path / "nodepth", n=8, labeled=4, height=32, width=48,
                                   seed=2, progress=False)
    for name in os.listdir(root / "depth"):
        cv2.imwrite(str(root / "depth" / name), np.zeros((32, 48), np.uint16))
    work = tmp_path / "w"
    code, _, err = run(["train", "stage2", "--data", root, "--workdir", work, *QUICK,
                        "stage2.preprocessing=he", "stage2.sky_loss=false"], capsys)
    one_line_error(code, err, str(root), "valid depth")
    assert not work.exists()


@pytest.mark.parametrize("text, needles", [
    ("x = 1\ndef get_config(:\n", ["line 2", "syntax error"]),
    ("x = 1\ny = 1 / 0\n", ["line 2", "ZeroDivisionError"]),
    ("def get_config():\n    raise KeyError('stage9')\n", ["line 2", "KeyError", "stage9"]),
])
def test_broken_python_config(data, tmp_path, capsys, text, needles):
    config = tmp_path / "c.py"
    config.write_text(text)
    code, _, err = run(train(data, tmp_path / "w", "--config", config), capsys)
    one_line_error(code, err, str(config), *needles)


@pytest.mark.parametrize("command", ["eval", "predict"])
def test_out_that_is_a_file(tmp_path, capsys, command):
    out = tmp_path / "taken"
    out.write_text("mine")
    argv = (["eval", "--workdir", tmp_path, "--data", tmp_path] if command == "eval"
            else ["predict", "--checkpoint", tmp_path, "frame.npy"])
    code, _, err = run(argv + ["--out", out], capsys)
    one_line_error(code, err, f"--out {out}", "not a directory")
    assert out.read_text() == "mine"


# --------------------------------------------------------------------------- nothing left behind
def test_failure_before_the_first_step_leaves_nothing(data, tmp_path, capsys, monkeypatch):
    """A refusal (one line, exit code 2) or a bug (its traceback) before the first step."""
    fresh, mine = tmp_path / "fresh", tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    for error in (RunError, ValueError):
        def broken(*args, error=error, **kwargs):
            raise error("optimizer broke")

        monkeypatch.setattr(stages, "stage1_optimizer", broken)
        for work in (fresh, mine):
            if error is RunError:
                code, _, err = run(train(data, work, "--steps", "2"), capsys)
                assert code == 2 and "irdepth: error: optimizer broke" in err and "Traceback" not in err
            else:
                with pytest.raises(ValueError, match="optimizer broke"):
                    run(train(data, work, "--steps", "2"), capsys)
        assert not fresh.exists()
        assert os.listdir(mine) == ["notes.txt"]
    monkeypatch.undo()
    code, _, err = run(train(data, fresh, "--steps", "1"), capsys)
    assert code == 0, err


# --------------------------------------------------------------------------- the lock
def write_lock(work, pid, host=None):
    work.mkdir(exist_ok=True)
    (work / LOCK_NAME).write_text(json.dumps({"pid": pid, "host": host or socket.gethostname()}))


def test_a_live_run_holds_the_workdir(data, tmp_path, capsys):
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        for work, host in ((tmp_path / "here", None), (tmp_path / "there", "otherhost")):
            write_lock(work, other.pid, host)
            code, _, err = run(train(data, work, "--resume-or-start"), capsys)
            one_line_error(code, err, f"pid {other.pid} on {host or socket.gethostname()}")
            assert os.listdir(work) == [LOCK_NAME]
    finally:
        other.kill()
        other.wait()


def test_stale_lock_and_resume_or_start(data, tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    work = tmp_path / "w"
    write_lock(work, dead.pid)
    code, _, err = run(train(data, work, "--steps", "1", "--resume-or-start"), capsys)
    assert code == 0, err
    assert f"taking over the lock {work / LOCK_NAME} of pid {dead.pid}" in err
    assert not (work / LOCK_NAME).exists()
    before = read_metrics(work)
    code, _, err = run(train(data, work, "--steps", "1", "--resume-or-start"), capsys)
    assert code == 0, err  # resumed the finished run: nothing to do
    assert read_metrics(work) == before


# --------------------------------------------------------------------------- Ctrl-C, torn lines
def test_second_ctrl_c_while_saving_lets_the_save_finish(data, tmp_path, capsys, monkeypatch):
    """Ctrl-C at step 2, again inside the stop's save and inside the final wait for it: the
    checkpoint is completed and named, without a traceback."""
    real_batch, real_meta = phase.device_batch, checkpoint._jsonable
    real_wait = ocp.CheckpointManager.wait_until_finished
    sent = {"batch": 0, "save": False, "wait": False}

    def batch(*args):
        sent["batch"] += 1
        if sent["batch"] == 2:
            signal.raise_signal(signal.SIGINT)
        return real_batch(*args)

    def meta(value):
        if sent["batch"] == 2 and not sent["save"]:
            sent["save"] = True
            signal.raise_signal(signal.SIGINT)
        return real_meta(value)

    def wait(self):
        if sent["save"] and not sent["wait"] and sys._getframe(1).f_code.co_name == "wait":
            sent["wait"] = True
            signal.raise_signal(signal.SIGINT)
        return real_wait(self)

    monkeypatch.setattr(phase, "device_batch", batch)
    monkeypatch.setattr(checkpoint, "_jsonable", meta)
    monkeypatch.setattr(ocp.CheckpointManager, "wait_until_finished", wait)
    work = tmp_path / "w"
    code, _, err = run(train(data, work, "--steps", "4"), capsys)
    assert sent == {"batch": 2, "save": True, "wait": True}
    assert code == 130, err
    assert "Traceback" not in err
    assert f"stage1_i1 checkpoint at step 2 in {work / 'checkpoints' / 'stage1_i1'}" in err
    assert "ignored so that it completes" in err
    steps = os.listdir(work / "checkpoints" / "stage1_i1")
    assert all(n.isdigit() for n in steps) and max(map(int, steps)) == 2  # finished, no tmp dir


def test_second_ctrl_c_aborts_and_torn_metrics_lines(data, tmp_path, capsys, monkeypatch):
    """A second Ctrl-C outside a save aborts at once, naming the last checkpoint; --resume then
    drops the torn last line a kill leaves in metrics.jsonl; a torn line elsewhere is an error."""
    real = phase.device_batch
    calls = {"n": 0}

    def batch(*args):
        calls["n"] += 1
        if calls["n"] == 3:
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGINT)
        return real(*args)

    monkeypatch.setattr(phase, "device_batch", batch)
    work = tmp_path / "w"
    args = train(data, work, "--steps", "4", "checkpoint_every=1")
    code, _, err = run(args, capsys)
    assert code == 130, err
    assert "Traceback" not in err
    assert f"the last checkpoint is {work / 'checkpoints' / 'stage1_i1'} step 2" in err
    monkeypatch.undo()

    metrics = work / "metrics.jsonl"
    torn_line = len(metrics.read_text().splitlines()) + 1
    with open(metrics, "a") as f:
        f.write('{"step": 3, "stage": "stage1_i1", "lo')
    code, _, err = run(args + ["--resume"], capsys)
    assert code == 0, err
    assert f"dropping the torn last line {torn_line} of {metrics}" in err
    assert [(r["stage"], r["step"]) for r in read_metrics(work) if r.get("kind") != "info"] == [
        ("stage1_i1", s) for s in range(1, 5)] + [("stage1_i2", s) for s in range(1, 5)]

    lines = metrics.read_text().splitlines(keepends=True)
    torn = "".join(lines[:1] + ['{"step": 2, "sta\n'] + lines[1:])
    metrics.write_text(torn)
    code, _, err = run(args + ["--resume"], capsys)
    one_line_error(code, err, f"{metrics} line 2")
    assert metrics.read_text() == torn
