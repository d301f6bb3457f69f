"""No false success on predict, video, export and eval (issue 43): what a hostile user tries on
these surfaces ends in complete outputs or a one-line error naming the file or setting, never
in "wrote" for work that did not happen. Timing-dependent cases (two runs at once, Ctrl-C while
a packet is written) are made deterministic with hooks. The shared tiny trained runs
(`trained_runs`): these tests check what is written and said, not what a model learnt."""

import json
import os
import pathlib
import threading

import cv2
import numpy as np
import pytest

from irdepth_jax import cli
from irdepth_jax.data.synthetic import render_scene

HEIGHT, WIDTH = 32, 48


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    """The CLI's `irdepth: error: ...` line, checked to be the only line and no traceback
    (predict's lines on what the model was trained on left out)."""
    lines = [ln for ln in err.strip().splitlines()
             if not ln.startswith(("irdepth: model ", "irdepth: WARNING: this model was trained"))]
    assert len(lines) == 1 and lines[0].startswith("irdepth: error: "), err
    return lines[0]


def write_frames(folder, seeds, height=HEIGHT, width=WIDTH):
    """16-bit PNG frames ``NNNN.png`` rendered from `seeds` into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, seed in enumerate(seeds):
        cv2.imwrite(str(folder / f"{k:04d}.png"), render_scene(seed, "day", height, width)["raw14"])
    return folder


@pytest.fixture(scope="module")
def model(stage2_run):
    """Workdir of the shared tiny Stage II run (`trained_runs`; frames of 32x48)."""
    return stage2_run


# --------------------------------------------------------------------------- 1. one run per --out
def test_two_predicts_into_one_out_folder(model, tmp_path, capsys, monkeypatch):
    """While run A writes its files (its first write held by a hook), run B into the same
    --out is refused, naming the folder and A's pid; A's files are then all A's."""
    from irdepth_jax import predict, predict_outputs

    a, b = write_frames(tmp_path / "a", range(4)), write_frames(tmp_path / "b", range(10, 14))
    solo = tmp_path / "solo"
    assert run(["predict", "--checkpoint", model, "--out", solo, "--no-progress", a], capsys)[0] == 0

    writing, go_on = threading.Event(), threading.Event()
    write_png = predict_outputs.write_png

    def held_write(path, image):
        if not writing.is_set():  # the first write (run A's) waits for run B to have ended
            writing.set()
            assert go_on.wait(120)
        write_png(path, image)

    monkeypatch.setattr(predict_outputs, "write_png", held_write)
    out, result = tmp_path / "out", {}
    first = threading.Thread(target=lambda: result.update(
        written=predict.predict_files(str(model), [str(a)], str(out)).written))
    first.start()
    try:
        assert writing.wait(120)
        code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                                 b], capsys)
    finally:
        go_on.set()
        first.join()
    line = one_error_line(err)
    assert code == 2 and "wrote" not in stdout
    assert f"--out folder {out} is in use by another run (pid {os.getpid()}" in line
    assert len(result["written"]) == 16
    assert sorted(os.listdir(out)) == sorted(os.listdir(solo))  # the lock is gone too
    for name in os.listdir(out):
        assert open(out / name, "rb").read() == open(solo / name, "rb").read(), name


# --------------------------------------------------------------------------- 2, 3. videos
@pytest.mark.parametrize("fps", ["inf", "nan", "0", "-5", "1e-9", "2000", "10000", "65536", "1e9"])
def test_video_frame_rate_out_of_range(model, tmp_path, capsys, fps):
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", tmp_path / "v", "--video",
                             "--fps", fps, tmp_path], capsys)
    line = one_error_line(err)
    assert code == 2 and "--fps" in line and "from 0.01 to 1000 frames per second" in line
    assert not (tmp_path / "v").exists() and "wrote" not in stdout


class _Container:
    """A PyAV output container whose `mux` goes through `on_mux(packets)` first (a hook that
    drops packets or raises), everything else forwarded."""

    def __init__(self, real, on_mux):
        self.real, self.on_mux = real, on_mux

    def mux(self, packets):
        self.real.mux(self.on_mux(list(packets)))

    def __getattr__(self, name):
        return getattr(self.real, name)


def hooked_writer(on_mux):
    """A VideoWriter class whose container's packets pass through `on_mux` (see _Container)."""
    pytest.importorskip("av", reason="PyAV (the video extra) is not installed")
    from irdepth_jax.video import VideoWriter

    class Hooked(VideoWriter):
        def _open(self, height, width):
            super()._open(height, width)
            self.container = _Container(self.container, on_mux)

    return Hooked


def lose_first_packets(interrupt: bool):
    """An `on_mux` that loses the first packets the encoder gives (the keyframe): dropped, or
    lost to a Ctrl-C landing while they are written (`interrupt`)."""
    state = {"lost": False}

    def on_mux(packets):
        if packets and not state["lost"]:
            state["lost"] = True
            if interrupt:
                raise KeyboardInterrupt
            return []
        return packets

    return on_mux


def ramp(n):
    return [np.full((16, 16, 3), 20 + 3 * k, np.uint8) for k in range(n)]


def test_a_video_that_does_not_decode_whole_is_not_written(tmp_path):
    """A video whose file decodes to fewer frames than were written (here: its first packets
    lost) is an error naming it, and nothing is left under its name."""
    from irdepth_jax.fileio import WriteError

    writer = hooked_writer(lose_first_packets(interrupt=False))
    with pytest.raises(WriteError, match=r"v\.mp4: not written: the file decodes to 0 of the 60 "
                                         r"frames written"):
        with writer(tmp_path / "v.mp4", fps=10) as video:
            for frame in ramp(60):
                video.write(frame)
    assert os.listdir(tmp_path) == []


def test_ctrl_c_while_the_first_packet_is_written_keeps_no_undecodable_partial(tmp_path):
    """x264 holds back its first packets (lookahead): Ctrl-C landing while they are muxed loses
    the keyframe; the partial file would decode to no frame, so none is kept."""
    writer = hooked_writer(lose_first_packets(interrupt=True))
    with pytest.raises(KeyboardInterrupt):
        with writer(tmp_path / "v.mp4", fps=10) as video:
            for frame in ramp(60):
                video.write(frame)
    assert video.frames > 0 and video.kept == 0
    assert os.listdir(tmp_path) == []


def test_predict_says_what_an_interrupted_video_kept(model, tmp_path, capsys, monkeypatch):
    from irdepth_jax import video

    monkeypatch.setattr(video, "VideoWriter", hooked_writer(lose_first_packets(interrupt=True)))
    drive = write_frames(tmp_path / "drive", range(48))
    out = tmp_path / "out"
    # the default batch size: the program the other predicts here compiled
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--video",
                             "--no-progress", drive], capsys)
    assert code == cli.EXIT_INTERRUPTED and "wrote" not in stdout
    assert "frames encoded before Ctrl-C do not decode as a video; nothing kept" in err, err
    assert "holds" not in err and os.listdir(out) == []


# --------------------------------------------------------------------------- 5. --out and inputs
def test_out_that_is_an_input_folder_is_refused(model, tmp_path, capsys):
    """Outputs written into the input folder would be read as raw frames by the next run on it
    (16-bit NAME_depth.png among them): refused before anything is written, also through a
    symlink."""
    frames = write_frames(tmp_path / "frames", range(2))
    (tmp_path / "link").symlink_to(frames)
    for out in (frames, tmp_path / "link", f"{frames}/."):
        code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                                 frames], capsys)
        line = one_error_line(err)
        assert code == 2 and f"--out {out} is the input folder {frames}" in line, line
        assert sorted(os.listdir(frames)) == ["0000.png", "0001.png"]


# --------------------------------------------------------------------------- 7. Stage I models
def test_a_stage1_model_says_it_has_no_depth(stage1_run, tmp_path, capsys):
    frames = write_frames(tmp_path / "frames", range(2))
    out = tmp_path / "out"
    code, stdout, err = run(["predict", "--checkpoint", stage1_run, "--out", out, "--no-progress",
                             frames], capsys)
    assert code == 0, err
    assert f"irdepth: note: {stage1_run} is a Stage I model, it has no depth output" in err
    assert f"wrote 4 files (pseudo-RGB and HSV images, no depth: a Stage I model) to {out}" in stdout
    assert sorted(os.listdir(out)) == ["0000_hsv.png", "0000_rgb.png", "0001_hsv.png",
                                       "0001_rgb.png"]
    code, stdout, err = run(["predict", "--checkpoint", stage1_run, "--out", tmp_path / "v",
                             "--video", "--depth-png", frames], capsys)
    line = one_error_line(err)
    assert code == 2 and f"--depth-png: {stage1_run} is a Stage I model" in line
    assert not (tmp_path / "v").exists()


# --------------------------------------------------------------------------- 6. MS2 without depth
def test_ms2_frames_without_depth_are_counted_and_strict_refuses(stage1_run, realdata, tmp_path, capsys):
    """4 of the 6 thermal frames of test_day (3 sequences of 2 frames) have no depth file: one
    warning line counts them (the 2 left are read), from the reader and from `irdepth eval`;
    --strict refuses, in eval and in train (before training)."""
    from ms2_layout import official_sequences, partial_ms2

    from irdepth_jax.data.folder import DatasetWarning
    from irdepth_jax.data.ms2 import MissingDepthError, MS2Dataset
    from irdepth_jax.data.source import DataSource

    lists = realdata / "ms2_lists"
    sequences = official_sequences(lists, "test_day_list.txt")
    assert len(sequences) == 3
    root = partial_ms2(lists, tmp_path / "ms2", sequences, frames=2, size=(HEIGHT, WIDTH))
    for seq in sequences[:2]:
        for k in range(2):
            (root / "proj_depth" / seq / "thr" / "depth_filtered" / f"{k:06d}.png").unlink()
    want = (f"{root}: 4 of 6 thermal frames of split 'test_day' have no depth file "
            "(proj_depth/<seq>/thr/depth_filtered/<name>.png)")
    with pytest.warns(DatasetWarning, match="4 of 6 thermal frames") as caught:
        assert len(MS2Dataset(root, "test_day")) == 2
    assert [str(w.message) for w in caught if "thermal frames" in str(w.message)] == [
        want + ", skipped"]
    with pytest.raises(MissingDepthError, match="4 of 6 thermal frames"):
        MS2Dataset(root, "test_day", strict=True)
    with pytest.raises(ValueError, match="4 of 6 thermal frames of split 'test_day' have no depth"):
        DataSource(str(root), strict=True).frames("test_day")

    evaluate = ["eval", "--workdir", stage1_run, "--data", root, "--split", "test_day"]
    code, _, err = run([*evaluate, "--out", tmp_path / "e"], capsys)
    assert code == 0, err
    assert [ln for ln in err.splitlines() if "depth file" in ln] == [
        f"irdepth: warning: {want}, skipped"], err
    result = json.loads((tmp_path / "e" / "eval_test_day.json").read_text())
    assert result["protocol"]["frames"] == 2 and result["stage1"]["all"]["count"] == 2
    code, _, err = run([*evaluate, "--strict", "--out", tmp_path / "strict"], capsys)
    assert code == 2 and want in one_error_line(err)
    assert not (tmp_path / "strict" / "eval_test_day.json").exists()
    for split in ("train", "val"):  # the same three sequences
        (root / f"{split}_list.txt").write_text("\n".join(sequences) + "\n")
    code, _, err = run(["train", "stage1", "--data", root, "--workdir", tmp_path / "w", "--strict"],
                       capsys)
    assert code == 2 and "4 of 6 thermal frames of split 'train' have no depth" in one_error_line(err)
    assert not (tmp_path / "w").exists()


# --------------------------------------------------------------------------- 4. data of a resume
def test_resume_on_a_replaced_dataset_is_refused(synthetic_data, tmp_path, capsys):
    """A run stopped with --stop-at, its dataset then replaced: frames added (said as such, not
    as a loader-state mismatch), or the same number of other frames; the resume is refused,
    naming the data and what changed. On the data it started with it resumes."""
    import shutil

    from trained_runs import DATA, QUICK, copy_run

    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    data, work = copy_run(synthetic_data, tmp_path / "data"), tmp_path / "run"
    argv = ["train", "stage1", "--data", data, "--workdir", work, "--steps", 2, *QUICK]
    code, _, err = run([*argv, "--stop-at", 1], capsys)
    assert code == cli.EXIT_INTERRUPTED and "stopped at step 1" in err, err
    for changed, phrase in (({"n": 32}, "stage1_i1: 5 frames added (16 -> 21)"),
                            ({"seed": 7}, "stage1_i1: ")):
        write_synthetic_dataset(data, **{**DATA, **changed}, progress=False, overwrite=True)
        code, stdout, err = run([*argv, "--resume"], capsys)
        assert code == 2 and "loader state" not in err, err
        assert (f"irdepth: error: --resume: the dataset changed since this run started "
                f"({work}/data_fingerprint.json): --data {data}: {phrase}") in err, err
    shutil.rmtree(data)
    copy_run(synthetic_data, data)
    code, stdout, err = run([*argv, "--resume"], capsys)
    assert code == 0 and "stage1 done" in stdout, err


# --------------------------------------------------------------------------- 8. corrupt checkpoints
@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_corrupt_checkpoint_is_one_line(stage2_run, tmp_path, capsys, damage):
    """A model data file of the last checkpoint truncated to half, or with its first 64 bytes
    inverted: predict stops with one line naming the checkpoint as corrupt."""
    from trained_runs import copy_run

    work = copy_run(stage2_run, tmp_path / "run")
    step = work / "checkpoints" / "stage2" / "2"
    data = max((step / "model").rglob("d/*"), key=lambda p: p.stat().st_size)
    blob = bytearray(data.read_bytes())
    if damage == "truncate":
        blob = blob[:len(blob) // 2]
    else:  # in its header (inverted weight values would read as non-finite weights)
        blob[:64] = bytes(b ^ 0xFF for b in blob[:64])
    data.write_bytes(bytes(blob))
    frames = write_frames(tmp_path / "frames", range(1))
    code, stdout, err = run(["predict", "--checkpoint", work, "--out", tmp_path / "out",
                             "--no-progress", frames], capsys)
    line = one_error_line(err)
    assert code == 2 and f"checkpoint {step.parent} step 2 is corrupt" in line, line
    assert len(line) < 250, line


# --------------------------------------------------------------------------- 10. damaged inputs
def test_corrupt_lzw_tiff_and_empty_npy_name_the_file(tmp_path):
    import tifffile

    from irdepth_jax.data.rawio import RawFileError, read_frames

    tiff = tmp_path / "lzw.tif"
    tifffile.imwrite(tiff, np.random.default_rng(0).integers(3000, 9000, (64, 80)).astype(
        np.uint16), compression="lzw")
    blob = bytearray(tiff.read_bytes())
    blob[1000:1200] = bytes(b ^ 0xFF for b in blob[1000:1200])  # inside the LZW strips
    tiff.write_bytes(bytes(blob))
    with pytest.raises(RawFileError, match=rf"^{tiff}: not a readable TIFF \(.*LZW"):
        read_frames(str(tiff))
    empty = tmp_path / "empty.npy"
    empty.write_bytes(b"")
    with pytest.raises(RawFileError, match=rf"^{empty}: not a readable .npy array"):
        read_frames(str(empty))


# --------------------------------------------------------------------------- 9. experiment caches
def test_a_cached_run_is_trained_by_one_runner(tmp_path):
    """Two experiment runners on one --cache: while one holds a cached run's workdir lock (taken
    here by the test), the other stops with one line instead of training into it; once the
    first has finished (trained.json), the second only reads its time."""
    import json
    import types

    from irdepth_experiments.cache import Context
    from irdepth_jax.train.phase import RunOptions
    from irdepth_jax.train.workdir_lock import acquire, release

    workdir = tmp_path / "runs" / "stage1-abc"
    workdir.mkdir(parents=True)
    trained = []
    runner = types.SimpleNamespace(cache=str(tmp_path), log=lambda line: None, source=None)
    runner._trained = lambda w: Context._trained(runner, w)
    cfg = types.SimpleNamespace(seed=0)
    opts = RunOptions(workdir=str(workdir))
    lock = acquire(str(workdir))  # the other runner, training
    try:
        with pytest.raises(SystemExit, match=rf"cached run {workdir} is in use by another run "
                                             rf"\(pid {os.getpid()}.*another runner on this --cache"):
            Context._train(runner, lambda *a: trained.append(a), "stage1", cfg, opts)
        assert trained == []
        (workdir / "trained.json").write_text(json.dumps({"wall_s": 12.5}))
    finally:
        release(lock)
    assert Context._train(runner, lambda *a: trained.append(a), "stage1", cfg, opts) == 12.5
    assert trained == [] and not (workdir / "irdepth.lock").exists()


def test_a_dataset_rendered_by_two_runners_at_once_is_never_rewritten(tmp_path, monkeypatch):
    """Two experiment runners on one --cache that both find the synthetic dataset missing: the
    second renders it while the first is rendering (a hook runs the first, whole, inside the
    second's render); the dataset the first returned, and may read, stays as it was (the same
    files, not re-written under it), and nothing else is left in the cache's data folder.
    Before, both rendered into the dataset's own folder, the second deleting the first's."""
    import dataclasses
    import types

    from irdepth_experiments.cache import Context
    from irdepth_jax.config import get_config
    from irdepth_jax.data import synthetic_dataset

    base = get_config("tiny")
    base = dataclasses.replace(base, data=dataclasses.replace(base.data, height=16, width=24))

    def runner():
        return types.SimpleNamespace(base=base, cache=str(tmp_path), log=lambda line: None,
                                     args=types.SimpleNamespace(no_progress=True))

    def files(path):
        return {str(p.relative_to(path)): p.stat().st_ino for p in sorted(path.rglob("*"))}

    real_write = synthetic_dataset.write_synthetic_dataset
    first = {}

    def write_while_the_first_runner_renders(*args, **kwargs):
        if not first:  # the second runner's render, started: the first runs whole meanwhile
            first["path"] = None
            first["path"], _ = Context._render(runner(), "synthetic", 3, 2, 0, None)
            first["files"] = files(pathlib.Path(first["path"]))
        return real_write(*args, **kwargs)

    monkeypatch.setattr(synthetic_dataset, "write_synthetic_dataset", write_while_the_first_runner_renders)
    second, _ = Context._render(runner(), "synthetic", 3, 2, 0, None)
    assert second == first["path"]
    dataset = pathlib.Path(second)
    assert "manifest.json" in first["files"] and len(first["files"]) > 3
    assert files(dataset) == first["files"]  # not one file replaced or removed
    assert os.listdir(dataset.parent) == [dataset.name]
    (dataset.parent / "eval-n3-16x24-seed0").mkdir()  # an older version's interrupted render
    with pytest.raises(SystemExit, match=r"eval-n3-16x24-seed0: an incomplete dataset \(no manifest"):
        Context._render(runner(), "eval-n3", 3, 3, 0, "test")


# --------------------------------------------------------------------------- extras
@pytest.mark.parametrize("call", ["sys.exit(3)", "sys.exit(0)", "exit()"])
def test_a_config_file_that_exits_is_reported(tmp_path, capsys, call):
    """A .py config calling sys.exit() made irdepth exit with its code and no word (exit 0 as
    if trained, for sys.exit(0)); now a one-line error naming the file, before any data is read."""
    config = tmp_path / "cfg.py"
    config.write_text(f"import sys\n{call}\n")
    code, stdout, err = run(["train", "stage1", "--data", tmp_path, "--workdir",
                             tmp_path / "w", "--config", config], capsys)
    line = one_error_line(err)
    assert code == 2 and f"--config {config}: the file called sys.exit(" in line, line
    assert not (tmp_path / "w").exists()


def test_export_check_frames_of_any_size():
    """`irdepth export --height 2 --width 2` failed with the renderer's 'height and width must
    be >= 8', about the check's synthetic frames, though the model takes any size (it edge-pads):
    the frames are rendered at 8 x 8 or more and cropped (measured: a 2x2 stablehlo export of
    the tiny model passes its check, max |diff| 7.6e-6 m)."""
    from irdepth_jax.data.synthetic import render_scene
    from irdepth_jax.export import sample_frames

    for shape in ((1, 2, 2), (2, 1, 9), (1, 8, 8)):
        frames = sample_frames(shape, 14)
        assert frames.shape == shape and frames.dtype == np.uint16
    want = render_scene(1, height=8, width=9)["raw14"][:1, :9]
    np.testing.assert_array_equal(sample_frames((2, 1, 9), 16)[1], want.astype(np.uint16) << 2)


def test_a_frame_too_large_for_the_memory_is_refused_before_anything_is_written(model, tmp_path,
                                                                                capsys, monkeypatch):
    """An 8000x8000 frame was killed by the kernel after minutes with no message: the compiled
    program's memory (XLA's estimate) is compared with the free memory before any frame runs
    (here the free memory is made 1 MiB), and refused in one line with both figures."""
    from irdepth_jax import predict_runner

    monkeypatch.setattr(predict_runner, "available_bytes", lambda: 2**20)
    frames = write_frames(tmp_path / "in", range(2))
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", tmp_path / "out",
                             "--no-progress", "--batch-size", "2", frames], capsys)
    line = one_error_line(err)
    assert code == 2 and "wrote" not in stdout
    assert f"a batch of 2 frames of {HEIGHT}x{WIDTH} needs about" in line and "1 MiB free" in line
    assert "--batch-size 1" in line and not (tmp_path / "out").exists()
    monkeypatch.setattr(predict_runner, "available_bytes", lambda: 2**40)
    assert run(["predict", "--checkpoint", model, "--out", tmp_path / "out", "--no-progress",
                frames], capsys)[0] == 0
