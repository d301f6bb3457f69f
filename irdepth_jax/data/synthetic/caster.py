"""Camera, ray casting and per-pixel geometry.

Camera: pinhole at height cam_h looking along +z, no pitch; by default focal length 0.9 * width
and the horizon at row 0.45 * height (the `varied` scenes draw both, see `render`). Every
primitive is an axis-aligned box, an ellipsoid or a wheel ring, intersected with all the rays of
its projected bounding box at once (ray directions separate into a row vector and a column
vector, so each intersection is a few broadcast numpy operations), into a z-buffer. Depth is the
z-depth (distance along the optical axis).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from irdepth_jax.data.synthetic.materials import GROUND, SKY
from irdepth_jax.data.synthetic.scene import Scene

# Normal codes of the face a ray hits: 0 = +-x, 1 = +-y, 2 = z (always -z: rays go to +z).
NX, NY, NZ = 0, 1, 2

_NEAR = 0.05  # near clipping plane (m)


@dataclasses.dataclass(frozen=True, eq=False)
class Geometry:
    """What the rays of an (H, W) image hit.

    dx (1, W), dy (H, 1) float32: ray direction (x / z, y / z) of each column / row; f, cy:
    focal length and horizon row (pixels); obj (H, W) int32 object id; kind (H, W) int32 its
    kind; nrm (H, W) int8 normal code (NX, NY, NZ); sky (H, W) bool; depth (H, W) float32
    z-depth, 0 on sky; x_w, y_w, z_w (H, W) float32 world coordinates of the hit (0 on sky);
    rng_m (H, W) float32 Euclidean range; elev (H, W) float32 elevation of each ray (rad).
    """

    dx: np.ndarray
    dy: np.ndarray
    f: float
    cy: float
    obj: np.ndarray
    kind: np.ndarray
    nrm: np.ndarray
    sky: np.ndarray
    depth: np.ndarray
    x_w: np.ndarray
    y_w: np.ndarray
    z_w: np.ndarray
    rng_m: np.ndarray
    elev: np.ndarray


def cast_scene(scene: Scene, kinds: np.ndarray, height: int, width: int, cam_h: float,
               camera: tuple[float, float, float] | None = None) -> Geometry:
    """Ray casts `scene` from a camera at height cam_h into an (H, W) = (height, width) image.

    Args:
      scene: the primitives.
      kinds: (N,) int kind of each of the scene's N objects (`Scene.table()['kind']`).
      height, width: image size; cam_h: camera height (m).
      camera: (f, cx, cy) focal length and principal point in pixels; None: the default
        camera (0.9 * width, width / 2, 0.45 * height).

    Returns:
      the per-pixel Geometry (arrays (H, W), rays (1, W) and (H, 1)).
    """
    cast = _Caster(height, width, cam_h, camera or (0.9 * width, width / 2.0, 0.45 * height))
    for b in sorted(scene.boxes, key=lambda b: b[4]):  # near to far: hidden boxes are skipped
        cast.box(*b)
    for e in scene.ellipsoids:
        cast.ellipsoid(*e)
    for r in scene.rings:
        cast.ring(*r)
    t = cast.t
    kind = kinds[cast.obj]
    sky = kind == SKY
    depth = np.where(sky, 0.0, t).astype(np.float32)
    return Geometry(
        dx=cast.dx, dy=cast.dy, f=cast.f, cy=cast.cy, obj=cast.obj, kind=kind, nrm=cast.nrm,
        sky=sky, depth=depth, x_w=np.where(sky, 0.0, t * cast.dx),
        y_w=np.where(sky, 0.0, cam_h + t * cast.dy), z_w=np.where(sky, 0.0, t),
        rng_m=depth * np.sqrt(cast.dx**2 + cast.dy**2 + 1.0),
        elev=np.arctan2(cast.dy, np.sqrt(1 + cast.dx**2)))


def _window(lo, hi, size):
    """Clip [lo, hi) to [0, size) -> (lo, hi) ints."""
    return max(0, min(size, math.floor(lo))), max(0, min(size, math.ceil(hi) + 1))


class _Caster:
    """Z-buffer ray caster over an (H, W) image; rays separate into rows (dy) and columns (dx).

    t (H, W) float32: nearest hit so far (the ground plane, inf above the horizon); obj (H, W)
    int32: its object id (GROUND or SKY to start with); nrm (H, W) int8: its normal code.
    """

    def __init__(self, height, width, cam_h, camera):
        self.h, self.w, self.oy = height, width, cam_h
        self.f, self.cx, self.cy = (float(v) for v in camera)
        dx = (np.arange(width, dtype=np.float32) + 0.5 - self.cx) / self.f
        dy = -(np.arange(height, dtype=np.float32) + 0.5 - self.cy) / self.f
        self.dx = np.where(np.abs(dx) < 1e-6, 1e-6, dx)[None, :]
        self.dy = np.where(np.abs(dy) < 1e-6, -1e-6, dy)[:, None]
        ground_t = np.where(self.dy < 0, cam_h / np.maximum(-self.dy, 1e-9), np.inf)
        self.t = np.broadcast_to(ground_t, (height, width)).astype(np.float32)
        self.obj = np.where(np.isfinite(self.t), GROUND, SKY).astype(np.int32)
        self.nrm = np.full((height, width), NY, np.int8)

    def _bbox(self, x0, x1, y0, y1, z0, z1):
        """Pixel window (v0, v1, u0, u1) covering the projection of a box, or None if empty.

        The projection of x / z is extreme at the box's corners, so 4 values per axis suffice
        (plain Python floats: this runs once per primitive and numpy's overhead would dominate).
        """
        z0, z1 = max(z0, _NEAR), max(z1, _NEAR)
        us = [self.cx + self.f * x / z for x in (x0, x1) for z in (z0, z1)]
        vs = [self.cy - self.f * (y - self.oy) / z for y in (y0, y1) for z in (z0, z1)]
        v0, v1 = _window(min(vs) - 0.5, max(vs) - 0.5, self.h)
        u0, u1 = _window(min(us) - 0.5, max(us) - 0.5, self.w)
        return None if v0 >= v1 or u0 >= u1 else (v0, v1, u0, u1)

    def _commit(self, win, t_hit, oid, nrm):
        """Z-test (v1 - v0, u1 - u0) hit distances t_hit in window win, keep the nearer ones."""
        v0, v1, u0, u1 = win
        cur = self.t[v0:v1, u0:u1]
        hit = t_hit < cur
        np.copyto(cur, t_hit, where=hit)
        np.copyto(self.obj[v0:v1, u0:u1], oid, where=hit)
        np.copyto(self.nrm[v0:v1, u0:u1], nrm, where=hit)

    def box(self, x0, x1, y0, y1, z0, z1, oid):
        """Draws the box [x0, x1] x [y0, y1] x [z0, z1] of object oid."""
        if z1 <= _NEAR:
            return
        win = self._bbox(x0, x1, y0, y1, z0, z1)
        if win is None:
            return
        v0, v1, u0, u1 = win
        if self.t[v0:v1, u0:u1].max() < z0:  # hidden behind what is drawn already
            return
        dx, dy = self.dx[:, u0:u1], self.dy[v0:v1]
        ax, bx = x0 / dx, x1 / dx
        ay, by = (y0 - self.oy) / dy, (y1 - self.oy) / dy
        tx_n, tx_f = np.minimum(ax, bx), np.maximum(ax, bx)
        ty_n, ty_f = np.minimum(ay, by), np.maximum(ay, by)
        t_near = np.maximum(np.maximum(tx_n, ty_n), z0)
        t_far = np.minimum(np.minimum(tx_f, ty_f), z1)
        ok = (t_near <= t_far) & (t_near > _NEAR)
        t_hit = np.where(ok, t_near, np.inf).astype(np.float32)
        nrm = np.where(tx_n >= ty_n, np.where(tx_n >= z0, NX, NZ),
                       np.where(ty_n >= z0, NY, NZ)).astype(np.int8)
        self._commit(win, t_hit, oid, nrm)

    def ellipsoid(self, cx, cy, cz, rx, ry, rz, oid):
        """Draws the ellipsoid of centre (cx, cy, cz) and radii (rx, ry, rz) of object oid."""
        if cz + rz <= _NEAR:
            return
        win = self._bbox(cx - rx, cx + rx, cy - ry, cy + ry, cz - rz, cz + rz)
        if win is None:
            return
        v0, v1, u0, u1 = win
        dx, dy = self.dx[:, u0:u1] / rx, self.dy[v0:v1] / ry
        dz = 1.0 / rz
        ox, oy, oz = -cx / rx, (self.oy - cy) / ry, -cz / rz
        a = dx * dx + dy * dy + dz * dz
        b = dx * ox + dy * oy + dz * oz
        c = ox * ox + oy * oy + oz * oz - 1.0
        disc = b * b - a * c
        t_hit = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        t_hit = np.where(t_hit > _NEAR, t_hit, np.inf).astype(np.float32)
        self._commit(win, t_hit, oid, np.int8(NZ))

    def ring(self, axis, plane, ca, cy, r_out, r_in, oid):
        """Wheel: annulus centred at height cy in the plane x = plane (axis 0, centre z = ca)
        or z = plane (axis 2, centre x = ca)."""
        if axis == 0:
            box = (plane, plane, cy - r_out, cy + r_out, ca - r_out, ca + r_out)
        else:
            box = (ca - r_out, ca + r_out, cy - r_out, cy + r_out, plane, plane)
        if box[5] <= _NEAR:
            return
        win = self._bbox(*box)
        if win is None:
            return
        v0, v1, u0, u1 = win
        dx, dy = self.dx[:, u0:u1], self.dy[v0:v1]
        if axis == 0:
            t = plane / dx
            a = t - ca
        else:
            t = np.full_like(dx, plane)
            a = t * dx - ca
        y = self.oy + t * dy - cy
        r2 = a * a + y * y
        ok = (r2 <= r_out**2) & (r2 >= r_in**2) & (t > _NEAR)
        self._commit(win, np.where(ok, t, np.inf).astype(np.float32), oid,
                     np.int8(NX if axis == 0 else NZ))
