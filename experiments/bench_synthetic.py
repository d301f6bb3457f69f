"""Frames per second of the synthetic renderer (`render_scene`, camera_like included) on one core.

    python experiments/bench_synthetic.py [--size 256x320] [--frames 60]

Prints one line per condition and the mean over all (wall clock, and CPU time of this process,
which is the figure to trust on a shared machine); also the share spent in camera_like.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core: numpy / OpenCV single-threaded

import time  # noqa: E402

import cv2  # noqa: E402

from irdepth_jax.data.synthetic import CONDITIONS, render_scene  # noqa: E402
from irdepth_jax.imaging.tonemap import camera_like  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="256x320")
    ap.add_argument("--frames", type=int, default=60, help="frames per condition")
    args = ap.parse_args(argv)
    height, width = map(int, args.size.lower().split("x"))
    cv2.setNumThreads(1)
    render_scene(0, "day", height, width)  # warm the caches (band table, noise tile, FPN)
    total_t, total_cpu, total_n = 0.0, 0.0, 0
    for cond in CONDITIONS:
        t0, c0 = time.perf_counter(), time.process_time()
        raws = [render_scene(seed, cond, height, width)["raw14"] for seed in range(args.frames)]
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        total_t, total_cpu, total_n = total_t + dt, total_cpu + dc, total_n + args.frames
        print(f"{cond:6s} {args.frames / dt:6.1f} frames/s wall, "
              f"{args.frames / dc:6.1f} frames/s of CPU time")
    t0 = time.perf_counter()
    for raw in raws:
        camera_like(raw)
    cam = (time.perf_counter() - t0) / len(raws)
    fps = total_n / total_t
    print(f"all    {fps:6.1f} frames/s wall, {total_n / total_cpu:6.1f} frames/s of CPU time at "
          f"{height}x{width} (one core; camera_like {cam * 1e3:.1f} ms of {1e3 / fps:.1f} ms "
          "per frame)")


if __name__ == "__main__":
    main()
