"""Procedural LWIR street scenes with exact depth and segmentation labels.

`render_scene(seed, condition, height, width)` builds a random street (road with lanes and
markings, sidewalks, buildings on both sides with windows, a far backdrop that closes the view,
moving and parked cars, bicycles with or without riders, trees, lamp poles, sky) and renders it
by ray casting: every primitive is an axis-aligned box, an ellipsoid or a wheel ring, intersected
with all the rays of its projected bounding box at once (ray directions separate into a row
vector and a column vector, so each intersection is a few broadcast numpy operations).

Camera: pinhole at height ~1.5 m looking along +z, no pitch, focal length 0.9 * width, horizon at
row 0.45 * height. Depth is the z-depth (distance along the optical axis, KITTI/MS2 convention).
`scenes='varied'` draws the camera's height, horizon row and roll per frame (one focal length) and
adds crossings, open ground and close obstacles, so that no fixed depth layout fits most frames
(the default 'street' distribution is what every committed dataset was rendered from).

The LWIR frame is built in radiometric units: each pixel gets a temperature and an emissivity
from its material and the condition, plus the reflected sky, mixed in 8-14 um band radiance,
attenuated by the atmosphere, then turned into 14-bit counts by a simulated camera (gain and
offset, fixed-pattern noise, vignetting, narcissus, temporal noise); the RGB frame is its
aligned visible twin.

Sky holds depth 0 in both `depth` (dense) and `depth_lidar` (0 = invalid, as in the folder
format); `seg == 0` marks it. Every other pixel has a dense depth < 232 m (the far backdrop
closes the view).

Modules, in the order data flows (each imports only those before it):
  materials   object kinds, labels, per-condition parameters and material tables;
  scene       random street layouts -> primitives (`Scene`, `sample_scene`);
  caster      camera and ray casting -> per-pixel `Geometry`;
  surface     sunlight and shadows, ground materials and markings, windows, car lights;
  radiometry  temperatures -> band radiance -> raw 14-bit counts and the 8-bit frame;
  visible     the RGB twin;
  render      `render_scene`, the LiDAR and the labels.
"""

from irdepth_jax.data.synthetic.materials import CONDITIONS
from irdepth_jax.data.synthetic.render import LIDAR_MAX_RANGE, VARIED_CAMERA, render_scene
from irdepth_jax.data.synthetic.scene import SCENES

__all__ = ["CONDITIONS", "LIDAR_MAX_RANGE", "SCENES", "VARIED_CAMERA", "render_scene"]
