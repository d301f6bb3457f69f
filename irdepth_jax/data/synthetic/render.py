"""`render_scene`: one labelled street scene, thermal and visible, with dense and LiDAR depth."""

from __future__ import annotations

import cv2
import numpy as np

from irdepth_jax.config import IGNORE_LABEL
from irdepth_jax.data.synthetic.caster import Geometry, cast_scene
from irdepth_jax.data.synthetic.materials import COND, CONDITIONS, KIND_SEG, SEG_ID
from irdepth_jax.data.synthetic.radiometry import render_lwir
from irdepth_jax.data.synthetic.scene import sample_scene
from irdepth_jax.data.synthetic.surface import shade_surfaces
from irdepth_jax.data.synthetic.visible import render_rgb
from irdepth_jax.imaging.tonemap import camera_like

LIDAR_MAX_RANGE = 80.0
"""Range limit (metres, Euclidean) of the simulated LiDAR."""


def render_scene(seed: int, condition: str = "day", height: int = 256, width: int = 320,
                 scenes: str = "street") -> dict:
    """Renders one random street scene.

    Args:
      seed: any int; the same (seed, condition, height, width, scenes) gives identical arrays.
      condition: 'day', 'dusk' or 'night'.
      height, width: image size in pixels (>= 8 each).
      scenes: the scene distribution (`scene.SCENES`): 'street' (a level camera at 1.4-1.6 m,
        focal length 0.9 * width, horizon at 0.45 * height, one straight street) or 'varied'
        (`VARIED_CAMERA`: camera height, field of view, horizon row and roll drawn per frame;
        crossings, open ground and close obstacles, see `scene.sample_scene`).

    Returns:
      dict with
        raw14 (H, W) uint16: LWIR counts in 0..16383;
        ir8 (H, W) uint8: `irdepth_jax.imaging.tonemap.camera_like(raw14)`;
        rgb (H, W, 3) uint8: aligned visible image (dark and noisy at night);
        depth (H, W) float32: dense z-depth in metres, 0 on sky;
        depth_lidar (H, W) float32: sparse LiDAR-like z-depth (scan lines, <= 80 m range,
          no sky returns), 0 where there is no return;
        valid (H, W) bool: depth_lidar > 0;
        seg (H, W) uint8: labels in CLASS_NAMES order, 255 unlabelled (sidewalk, grass,
          poles, lamps, riders);
        condition str.
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    if height < 8 or width < 8:
        raise ValueError(f"height and width must be >= 8, got {height}x{width}")
    rng = np.random.default_rng(seed)
    scene, lay = sample_scene(rng, scenes)
    if scenes == "street":
        cam_h, canvas, camera = rng.uniform(1.4, 1.6), (height, width), None
    else:
        cam_h, roll, canvas, camera, horizon = _varied_camera(rng, height, width)
    tab = scene.table()
    geo = cast_scene(scene, tab["kind"], *canvas, cam_h, camera)
    t_air, sun_dir = _sample_lighting(rng, condition)
    surf = shade_surfaces(geo, scene, lay, tab, sun_dir)
    raw14, ir8 = render_lwir(rng, condition, t_air, geo, surf, tab["toff"])
    rgb = render_rgb(rng, condition, geo, surf, tab["color"], lay["lamps"], sun_dir)
    seg = np.where(surf.ground, np.where(surf.road, SEG_ID["road"], IGNORE_LABEL),
                   KIND_SEG[geo.kind]).astype(np.uint8)
    depth, depth_lidar = geo.depth, _lidar(rng, geo)
    if scenes != "street":
        raw14, rgb, depth, depth_lidar, seg = _roll(roll, camera, horizon, (height, width),
                                                    raw14, rgb, depth, depth_lidar, seg)
        ir8 = camera_like(raw14)
    return dict(raw14=raw14, ir8=ir8, rgb=rgb, depth=depth, depth_lidar=depth_lidar,
                valid=depth_lidar > 0, seg=seg, condition=condition)


STREET_HFOV_DEG = float(np.degrees(2 * np.arctan(0.5 / 0.9)))  # focal length 0.9 x width
VARIED_CAMERA = dict(height_m=(1.3, 1.7), hfov_deg=(STREET_HFOV_DEG, STREET_HFOV_DEG),
                     horizon=(0.25, 0.65), roll_deg=(-10.0, 10.0))
"""The `varied` scenes' camera, drawn uniformly per frame: height above the ground (a car's
mounting under load), horizontal field of view (fixed: one camera), the horizon's row as a
fraction of the image height (the principal point: the tilt of a level camera's sensor, so depth
stays the z-depth along the level optical axis) and the roll about the optical axis.

The field of view is fixed and the height varies little because a single image cannot tell them:
on the ground, row r below the horizon is at z = h f / r while a car's or a lane's width in
pixels there is W r / h, whatever f, so frames of different focal lengths look alike and their
depths differ by the ratio of the focal lengths; h shows only through the sizes of known objects.
A first version drew h from 0.8-3 m and the field of view from 45-95 degrees: its depth was
unidentifiable from the image by a factor of up to 9.9, and a depth network pretrained on it
plateaued near δ<1.25 0.42 (a network that reads the shape perfectly but not the scale gets
about 0.49 from the height range alone). What a network that ignores the image gets is in
tests/test_synthetic.py (0.39 here, 0.69 on the straight street)."""


def _varied_camera(rng, height, width):
    """(cam_h, roll radians, canvas (H', W'), (f, cx, cy) on the canvas, output horizon row) of
    a `varied` frame.

    A rolled frame is rendered level on a canvas large enough to hold the output frame rotated
    about the principal point, then rotated (`_roll`); the principal point sits at
    (width / 2, horizon row) of the output frame."""
    c = VARIED_CAMERA
    cam_h = rng.uniform(*c["height_m"])
    f = 0.5 * width / np.tan(np.deg2rad(rng.uniform(*c["hfov_deg"])) / 2)
    cy = rng.uniform(*c["horizon"]) * height
    roll = np.deg2rad(rng.uniform(*c["roll_deg"]))
    lo_out, hi_out = np.array([-width / 2, -cy]), np.array([width / 2, height - cy])
    corners = np.array([[u, v] for u in (lo_out[0], hi_out[0]) for v in (lo_out[1], hi_out[1])])
    on_canvas = corners @ _rotation(roll).T
    # whole-pixel margins around the output frame, so that without roll the canvas is the frame
    # shifted by whole pixels (an exact crop)
    before = np.ceil(np.maximum(lo_out - on_canvas.min(0), 0)) + 1
    after = np.ceil(np.maximum(on_canvas.max(0) - hi_out, 0)) + 1
    canvas = (int(height + before[1] + after[1]), int(width + before[0] + after[0]))
    camera = (float(f), float(width / 2 + before[0]), float(cy + before[1]))
    return cam_h, float(roll), canvas, camera, float(cy)


def _rotation(roll):
    """(2, 2) rotation taking output-frame offsets from the principal point to canvas offsets."""
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, s], [-s, c]])


def _roll(roll, camera, horizon, size, raw14, rgb, depth, depth_lidar, seg):
    """The canvas maps rotated by `roll` about the principal point into the (H, W) = size frame:
    counts and colours interpolated bilinearly, depth and labels by nearest neighbour (no
    mixed depths or classes at edges). z-depth is unchanged by a roll about the optical axis.
    The canvas's camera noise (fixed pattern, vignetting) rolls with it."""
    height, width = size
    rot = _rotation(roll)
    # OpenCV's pixel coordinates put pixel centres on integers; ours at + 0.5
    src_centre = np.array(camera[1:]) - 0.5
    dst_centre = np.array([width / 2.0, horizon]) - 0.5
    m = np.hstack([rot, (src_centre - rot @ dst_centre)[:, None]])

    def warp(a, interp):
        return cv2.warpAffine(a, m, (width, height), flags=interp | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)

    return (warp(raw14, cv2.INTER_LINEAR), warp(rgb, cv2.INTER_LINEAR), warp(depth, cv2.INTER_NEAREST),
            warp(depth_lidar, cv2.INTER_NEAREST), warp(seg, cv2.INTER_NEAREST))


def _sample_lighting(rng, condition):
    """Air temperature (K) and the (3,) unit vector toward the sun (None at night)."""
    p = COND[condition]
    t_air = rng.uniform(*p["t_air"]) + 273.15
    if p["sun_el"] is None:
        return t_air, None
    el, az = np.deg2rad(rng.uniform(*p["sun_el"])), rng.uniform(-np.pi, np.pi)
    return t_air, np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


def _lidar(rng, geo: Geometry):
    """(H, W) float32 sparse LiDAR-like depth: scan lines at uniform elevations, ~2 px azimuth
    step, dropouts, range noise, no return beyond LIDAR_MAX_RANGE or on sky."""
    depth = geo.depth
    height, width = depth.shape
    n_beams = max(8, height // 4)
    el = np.linspace(np.arctan(-(height - geo.cy) / geo.f), np.deg2rad(10.0), n_beams)
    rows = np.round(geo.cy - geo.f * np.tan(el) - 0.5)
    rows = np.unique(np.clip(rows, 0, height - 1)).astype(int)
    step = 2 if width >= 160 else 1
    mask = np.zeros((height, width), bool)
    phase = rng.integers(0, step, len(rows))
    for r, ph in zip(rows, phase):  # one slice assignment per scan line
        mask[r, ph::step] = True
    mask &= rng.random((height, width)) > 0.08
    noise = 1 + 0.003 * rng.standard_normal((height, width), dtype=np.float32)  # ~ +-3 mm/m
    mask &= (depth > 0) & (geo.rng_m * noise <= LIDAR_MAX_RANGE)
    return np.where(mask, depth * noise, 0).astype(np.float32)
