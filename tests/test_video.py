"""`irdepth_jax.video`: MP4 files that hold every frame written, at the right size, or nothing."""

import os

import numpy as np
import pytest

pytest.importorskip("av", reason="PyAV (the video extra) is not installed")

from irdepth_jax.fileio import WriteError  # noqa: E402
from irdepth_jax.video import VideoWriter, even_size, read_video, video_info  # noqa: E402


def ramp_frames(n, height, width):
    """Frames whose mean grey level steps by 24 per frame (survives H.264 compression)."""
    return [np.full((height, width, 3), 20 + 24 * k, np.uint8) for k in range(n)]


def test_round_trip_keeps_every_frame_in_order(tmp_path):
    path = tmp_path / "v.mp4"
    with VideoWriter(path, fps=15) as video:
        for frame in ramp_frames(8, 48, 96):
            video.write(frame)
    assert video_info(path) == {"frames": 8, "height": 48, "width": 96, "fps": 15.0}
    decoded = read_video(path)
    np.testing.assert_allclose(decoded.mean(axis=(1, 2, 3)), 20 + 24 * np.arange(8), atol=2)
    assert os.listdir(tmp_path) == ["v.mp4"]


def test_odd_sides_are_padded_to_even(tmp_path):
    assert even_size(31, 45) == (32, 46) and even_size(32, 46) == (32, 46)
    with VideoWriter(tmp_path / "odd.mp4", fps=10) as video:
        for frame in ramp_frames(3, 31, 45):
            video.write(frame)
    info = video_info(tmp_path / "odd.mp4")
    assert (info["frames"], info["height"], info["width"]) == (3, 32, 46)


def test_a_frame_of_another_size_fails_and_leaves_nothing(tmp_path):
    with pytest.raises(WriteError, match=r"frame 1 is 32x32, the video's frames are 16x16"):
        with VideoWriter(tmp_path / "v.mp4", fps=10) as video:
            video.write(np.zeros((16, 16, 3), np.uint8))
            video.write(np.zeros((32, 32, 3), np.uint8))
    assert os.listdir(tmp_path) == []
    with pytest.raises(WriteError, match="uint8"):
        VideoWriter(tmp_path / "w.mp4", fps=10).write(np.zeros((16, 16, 3), np.float32))
    assert os.listdir(tmp_path) == []


def test_interrupted_video_keeps_its_frames_as_partial(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with VideoWriter(tmp_path / "v.mp4", fps=10) as video:
            for frame in ramp_frames(5, 16, 16):
                video.write(frame)
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["v.partial.mp4"]
    assert video_info(tmp_path / "v.partial.mp4")["frames"] == 5


def test_bad_frame_rate_and_unwritable_folder(tmp_path):
    with pytest.raises(WriteError, match="frame rate 0"):
        VideoWriter(tmp_path / "v.mp4", fps=0)
    with pytest.raises(WriteError, match="no_such_dir"):
        with VideoWriter(tmp_path / "no_such_dir" / "v.mp4", fps=10) as video:
            video.write(np.zeros((16, 16, 3), np.uint8))
