"""`irdepth predict` on folders as users have them: a bad frame among good ones, same-named
frames in two folders, and a tree of folders (--recursive). An untrained tiny model: these
tests check which files are read and where the outputs go, not what the model learnt."""

import os

import cv2
import numpy as np
import pytest

from irdepth_jax import cli

H, W = 32, 48
KINDS = ("depth", "depth_color", "hsv", "rgb")


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def outputs(name):
    return [f"{name}_{kind}.png" for kind in KINDS]


def frame(path, value, dtype=np.uint16):
    """Writes a (H, W) 16-bit PNG of counts from `value` up (a pattern that differs by value)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    raw = value + np.arange(H * W).reshape(H, W) * (value // 1000) % 500
    assert cv2.imwrite(str(path), raw.astype(dtype))
    return path


def files_under(root):
    return sorted(os.path.relpath(os.path.join(d, n), root) for d, _, names in os.walk(root)
                  for n in names)


@pytest.fixture(scope="module")
def model(untrained_model):
    """The workdir of an untrained tiny Stage II model (14-bit counts)."""
    return untrained_model[0]


def test_a_16bit_frame_among_14bit_ones_is_skipped_and_named_at_the_end(model, tmp_path, capsys):
    """Counts over 14 bits are never clipped (the frame would be read at the wrong scale): the
    frame is left out, the others are written, one line at the end names it and why, and the
    exit status says that files were skipped. --strict stops at it before writing anything."""
    folder = tmp_path / "drive"
    for k in range(3):
        frame(folder / f"f{k}.png", 5000 + 1000 * k)
    hot = frame(folder / "f3_16bit.png", 40000)
    (folder / "f4_broken.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                             folder], capsys)
    assert code == cli.EXIT_SKIPPED == 1, err
    assert sorted(os.listdir(out)) == sorted(o for k in range(3) for o in outputs(f"f{k}"))
    assert "wrote 12 files" in stdout
    last = err.strip().splitlines()[-1]
    assert last.startswith("irdepth: skipped 2 of 5 files, not readable as raw frames: "), err
    hot_max = cv2.imread(str(hot), cv2.IMREAD_UNCHANGED).max()
    assert f"{hot} (raw counts exceed 14 bits: maximum {hot_max} > 16383" in last
    assert "--raw-bits 16" in last and f"{folder / 'f4_broken.png'} (" in last

    code, stdout, err = run(["predict", "--checkpoint", model, "--out", tmp_path / "strict",
                             "--strict", folder], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and stdout == "", err
    assert lines[0].startswith(f"irdepth: error: {hot}: raw counts exceed 14 bits"), err
    assert not (tmp_path / "strict").exists()

    code, _, err = run(["predict", "--checkpoint", model, "--out", tmp_path / "none", hot],
                       capsys)  # nothing left to predict: an error, no output
    assert code == 2 and err.startswith(f"irdepth: error: {hot}: raw counts exceed 14 bits"), err
    assert "no frame left to predict" in err and not (tmp_path / "none").exists()


def test_same_named_frames_of_two_folders_go_to_their_own_sub_folders(model, tmp_path, capsys):
    """Two camera folders both named thr, and a third, all with a frame 000001.png: each
    input's outputs go to a sub-folder of --out named after its folder, with the parent
    folder where the names collide too; each holds its own frame's prediction."""
    inputs = [tmp_path / "day1" / "thr", tmp_path / "day2" / "thr", tmp_path / "night"]
    for k, folder in enumerate(inputs):
        frame(folder / "000001.png", 3000 + 4000 * k)
    frame(inputs[2] / "000002.png", 6000)
    out = tmp_path / "out"
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                             *inputs], capsys)
    assert code == 0, err
    assert "same name '000001'" in err and "(day1/thr/, day2/thr/, night/)" in err
    assert files_under(out) == sorted(
        [os.path.join(d, o) for d in ("day1/thr", "day2/thr") for o in outputs("000001")]
        + [os.path.join("night", o) for n in ("000001", "000002") for o in outputs(n)])
    depths = [cv2.imread(str(out / d / "000001_hsv.png")) for d in ("day1/thr", "day2/thr")]
    assert np.abs(depths[0].astype(int) - depths[1]).max() > 0  # two frames, not one twice

    alone = tmp_path / "alone"  # each is the prediction of its own frame
    assert run(["predict", "--checkpoint", model, "--out", alone, "--no-progress", inputs[1]],
               capsys)[0] == 0
    for kind in KINDS:
        assert np.array_equal(cv2.imread(str(alone / f"000001_{kind}.png"), cv2.IMREAD_UNCHANGED),
                              cv2.imread(str(out / "day2/thr" / f"000001_{kind}.png"),
                                         cv2.IMREAD_UNCHANGED)), kind

    files = tmp_path / "files"  # a file named on the command line goes to its folder's name
    code, _, err = run(["predict", "--checkpoint", model, "--out", files, "--no-progress",
                        inputs[2], inputs[0] / "000001.png"], capsys)
    assert code == 0, err
    assert files_under(files) == sorted(
        [os.path.join("thr", o) for o in outputs("000001")]
        + [os.path.join("night", o) for n in ("000001", "000002") for o in outputs(n)])


def test_recursive_mirrors_the_input_tree(model, tmp_path, capsys):
    """--recursive reads every folder of the tree (colour images in it skipped as usual) and
    writes each frame's outputs at its relative path under --out; without it, sub-folders are
    not read; an --out inside the tree is refused."""
    root = tmp_path / "flight"
    frame(root / "a.png", 4000)
    frame(root / "seq1" / "a.png", 5000)
    frame(root / "seq1" / "left" / "b.png", 6000)
    (root / "seq1" / "rgb").mkdir()
    cv2.imwrite(str(root / "seq1" / "rgb" / "c.png"), np.zeros((H, W, 3), np.uint8))
    out = tmp_path / "out"
    code, _, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                        "--recursive", root], capsys)
    assert code == 0, err
    assert "skipped 1 of 4 files that are not raw thermal frames (8-bit or colour): c.png" in err
    assert files_under(out) == sorted(
        outputs("a") + [os.path.join("seq1", o) for o in outputs("a")]
        + [os.path.join("seq1", "left", o) for o in outputs("b")])

    flat = tmp_path / "flat"
    assert run(["predict", "--checkpoint", model, "--out", flat, "--no-progress", root],
               capsys)[0] == 0
    assert files_under(flat) == outputs("a")

    inside = root / "seq1" / "preds"
    code, _, err = run(["predict", "--checkpoint", model, "--out", inside, "-r", root], capsys)
    assert code == 2 and f"--out {inside} is inside the input folder {root}" in err, err
    assert not inside.exists()


def test_recursive_video_per_folder(model, tmp_path, capsys):
    """With --video, each folder of the tree is one sequence: its video at the folder's
    relative path (.mp4) under --out, its depth PNGs (--depth-png) in the mirrored folder."""
    pytest.importorskip("av", reason="the video extra (PyAV) is not installed")
    root = tmp_path / "drives"
    for seq in ("d1", "d2/left"):
        for k in range(2):
            frame(root / seq / f"{k}.png", 4000 + 1000 * k)
    out = tmp_path / "out"
    code, stdout, err = run(["predict", "--checkpoint", model, "--out", out, "--no-progress",
                             "--video", "--depth-png", "-r", root], capsys)
    assert code == 0, err
    assert "wrote 2 videos and 4 files" in stdout
    assert files_under(out) == ["d1.mp4", "d1/0_depth.png", "d1/1_depth.png", "d2/left.mp4",
                                "d2/left/0_depth.png", "d2/left/1_depth.png"]
