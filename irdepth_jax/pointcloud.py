"""Point clouds from depth maps (`irdepth predict --pointcloud`): pinhole back-projection with
the thermal camera's intrinsics, written as binary PLY (one coloured point per valid pixel).

Intrinsics come as ``fx,fy,cx,cy`` (pixels) or as a calibration file: MS2's ``calib.npy`` (a
pickled dict whose ``K_thrL`` is the left thermal camera's 3x3 matrix) or a ``.npy`` holding a
3x3 matrix.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

from irdepth_jax.errors import RunError

MS2_THERMAL_KEY = "K_thrL"
"""The left thermal camera's 3x3 intrinsic matrix in MS2's calib.npy."""


class Intrinsics(NamedTuple):
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float


def parse_intrinsics(spec: str) -> Intrinsics:
    """``fx,fy,cx,cy`` or a calibration file (module docstring) -> `Intrinsics`.
    RunError naming --intrinsics for anything else."""
    if os.path.isfile(spec):
        return _from_file(spec)
    parts = spec.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise RunError(f"`intrinsics` {spec}: expected fx,fy,cx,cy in pixels (fx, fy > 0) or a "
                       "calibration file (MS2's calib.npy, or a .npy 3x3 matrix)")
    return Intrinsics(*values)


def _from_file(path: str) -> Intrinsics:
    try:
        loaded = np.load(path, allow_pickle=True)
    except (ValueError, OSError) as err:
        raise RunError(f"`intrinsics` {path}: not a readable .npy file ({err})") from None
    if loaded.dtype == object and loaded.shape == ():  # MS2: a dict of matrices
        calib = loaded.item()
        if not isinstance(calib, dict) or MS2_THERMAL_KEY not in calib:
            keys = sorted(calib) if isinstance(calib, dict) else type(calib).__name__
            raise RunError(f"`intrinsics` {path}: no {MS2_THERMAL_KEY} (the thermal camera's "
                           f"matrix) in it; it holds {keys}")
        loaded = calib[MS2_THERMAL_KEY]
    matrix = np.asarray(loaded, np.float64)
    if matrix.shape != (3, 3):
        raise RunError(f"`intrinsics` {path}: a {matrix.shape} array, expected a 3x3 intrinsic "
                       "matrix")
    return Intrinsics(matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2])


def back_project(depth: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) -> (points (N, 3) float32 x right, y down, z forward, in the depth's unit;
    valid (H, W) bool), one point per valid pixel (finite depth > 0), in row-major order."""
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    z = depth[valid].astype(np.float64)
    points = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], axis=-1)
    return points.astype(np.float32), valid


def ply_bytes(points: np.ndarray, colors: np.ndarray) -> bytes:
    """A binary little-endian PLY of points (N, 3) float32 and colours (N, 3) uint8 RGB."""
    vertex = np.empty(len(points), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, name in enumerate("xyz"):
        vertex[name] = points[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        vertex[name] = colors[:, i]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    return header.encode() + vertex.tobytes()


def point_cloud_ply(depth: np.ndarray, image: np.ndarray, k: Intrinsics) -> bytes:
    """The PLY of one frame: depth (H, W) back-projected, coloured by image (H, W, 3) uint8 RGB."""
    points, valid = back_project(depth, k)
    return ply_bytes(points, image[valid])
