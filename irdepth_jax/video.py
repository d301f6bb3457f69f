"""Depth videos: H.264 MP4 files written frame by frame with PyAV (the FFmpeg libraries,
bundled in its wheel: no ffmpeg binary needed; the `video` extra).

`VideoWriter` streams frames into a temporary file beside the target and renames it into place
when it is closed, so a video is complete or absent under its name, as every other output
(`irdepth_jax.fileio`). H.264's 4:2:0 colour needs even sides: an odd height or width is padded
by one repeated edge row / column. An interrupted run keeps the frames encoded so far in
``NAME.partial.mp4`` (`VideoWriter.keep_partial`). A finished file is decoded and its frames
counted before it takes its name: a video missing frames is an error, never "written", and a
partial one that decodes to no frame is removed.
"""

from __future__ import annotations

import contextlib
import math
import os
import uuid

import numpy as np

from irdepth_jax.fileio import WriteError, describe_disk, disk_full

CODEC = "libx264"
PIXEL_FORMAT = "yuv420p"
QUALITY_CRF = "18"
"""x264's constant rate factor: 18 is visually lossless for these false-colour panels."""
MIN_FPS, MAX_FPS = 0.01, 1000.0
"""The frame rates a video may have. The MP4 stores the rate as a fraction (denominator at most
1001); past 1000 frames/s, beyond any thermal camera's rate, written files were seen to decode
to fewer frames than were written (and an infinite rate cannot be stored at all)."""


def fps_problem(fps: float) -> str | None:
    """Why `fps` cannot be a video's frame rate (None when it can)."""
    if not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        return f"must be a number from {MIN_FPS:g} to {MAX_FPS:g} frames per second"
    return None


def _import_av():
    try:
        import av
    except ImportError:
        raise WriteError("writing a video needs PyAV: pip install 'irdepth_jax[video]'") from None
    return av


def even_size(height: int, width: int) -> tuple[int, int]:
    """The encoded frame size of an (height, width) frame: each side rounded up to even."""
    return height + height % 2, width + width % 2


class VideoWriter:
    """An MP4 file of RGB frames (H, W, 3) uint8, all of one size, written in order.

    Usage: ``with VideoWriter(path, fps=15) as video: video.write(frame)``; leaving the block
    normally finalises the file and renames it to `path`; an exception (or `abort`) removes it.
    Errors (a frame of another size or dtype, a failed write, e.g. a full disk) raise
    `WriteError` naming `path`.
    """

    def __init__(self, path: str | os.PathLike, fps: float):
        problem = fps_problem(fps)
        if problem:
            raise WriteError(f"{os.fspath(path)}: frame rate {fps:g}: {problem}")
        self.av = _import_av()
        self.path = os.fspath(path)
        folder, name = os.path.split(os.path.abspath(self.path))
        self.tmp = os.path.join(folder, f".{name}.{uuid.uuid4().hex[:8]}.tmp.mp4")
        self.fps = fps
        self.frames = 0
        self.kept = 0
        """Frames `keep_partial` kept (those its file decodes to)."""
        self.size: tuple[int, int] | None = None
        self.container = self.stream = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif issubclass(exc_type, KeyboardInterrupt):
            self.keep_partial()
        else:
            self.abort()

    def _fail(self, err: BaseException, what: str = "not written") -> WriteError:
        self._drop()
        disk = f" on {describe_disk(os.path.dirname(self.tmp))}" if disk_full(err) else ""
        return WriteError(f"{self.path}: {what}: {getattr(err, 'strerror', None) or err}{disk}")

    def _open(self, height: int, width: int) -> None:
        from fractions import Fraction

        self.size = (height, width)
        try:
            self.container = self.av.open(self.tmp, mode="w", format="mp4")
            self.stream = self.container.add_stream(CODEC, rate=Fraction(self.fps).limit_denominator(1001))
            self.stream.height, self.stream.width = even_size(height, width)
            self.stream.pix_fmt = PIXEL_FORMAT
            self.stream.options = {"crf": QUALITY_CRF}
        except (OSError, self.av.FFmpegError) as err:
            raise self._fail(err) from err

    def write(self, frame: np.ndarray) -> None:
        """Appends one RGB frame (H, W, 3) uint8 (the first frame fixes the size)."""
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise self._fail(ValueError(f"expected an RGB frame (H, W, 3) uint8, got "
                                        f"{frame.dtype} {frame.shape}"))
        if self.size is None:
            self._open(*frame.shape[:2])
        elif frame.shape[:2] != self.size:
            raise self._fail(ValueError(
                f"frame {self.frames} is {frame.shape[0]}x{frame.shape[1]}, the video's "
                f"frames are {self.size[0]}x{self.size[1]} (one video holds one frame size)"))
        h, w = even_size(*self.size)
        if (h, w) != self.size:
            frame = np.pad(frame, ((0, h - self.size[0]), (0, w - self.size[1]), (0, 0)), "edge")
        try:
            picture = self.av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            self.container.mux(self.stream.encode(picture))
        except (OSError, self.av.FFmpegError) as err:
            raise self._fail(err) from err
        self.frames += 1

    def _finish(self, target: str, whole: bool) -> int:
        """Flushes the encoder, closes the file, decodes it and renames it to `target` when it
        decodes to every frame written (`whole`) or to at least one; returns that count."""
        if self.container is None:
            raise self._fail(ValueError("no frame was written"))
        try:
            self.container.mux(self.stream.encode(None))
            self.container.close()
            self.container = None
            decoded = _decoded_frames(self.av, self.tmp)
            if decoded == 0 or (whole and decoded != self.frames):
                raise ValueError(f"the file decodes to {decoded} of the {self.frames} frames "
                                 "written")
            os.replace(self.tmp, target)
        except (OSError, ValueError, self.av.FFmpegError) as err:
            raise self._fail(err) from err
        return decoded

    def close(self) -> int:
        """Finalises the video under its name; returns the number of frames."""
        return self._finish(self.path, whole=True)

    def partial_path(self) -> str:
        """Where `keep_partial` puts an interrupted video: ``NAME.partial.mp4``."""
        return os.path.splitext(self.path)[0] + ".partial.mp4"

    def keep_partial(self) -> str | None:
        """Finalises the frames written so far as `partial_path`, `kept` of them decodable (None,
        and no file, when none is: e.g. an interruption that lost the first keyframe)."""
        if self.container is None:
            return None
        try:
            self.kept = self._finish(self.partial_path(), whole=False)
        except WriteError:
            return None
        return self.partial_path()

    def abort(self) -> None:
        """Removes the unfinished file; nothing is left under the video's name."""
        self._drop()

    def _drop(self) -> None:
        if self.container is not None:
            with contextlib.suppress(Exception):
                self.container.close()
            self.container = None
        with contextlib.suppress(OSError):
            os.remove(self.tmp)


def _decoded_frames(av, path: str) -> int:
    """The number of frames a video file decodes to (0 for a file FFmpeg cannot read)."""
    try:
        with av.open(path) as container:
            return sum(1 for _ in container.decode(container.streams.video[0]))
    except (av.FFmpegError, IndexError):
        return 0


def video_info(path: str | os.PathLike) -> dict:
    """``{'frames', 'height', 'width', 'fps'}`` of a video file, its frames decoded and counted
    (the container's own frame count is not always written)."""
    av = _import_av()
    with av.open(os.fspath(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return {"frames": frames, "height": stream.height, "width": stream.width,
                "fps": float(stream.average_rate or 0)}


def read_video(path: str | os.PathLike) -> np.ndarray:
    """All frames of a video file as (N, H, W, 3) uint8 RGB."""
    av = _import_av()
    with av.open(os.fspath(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])
