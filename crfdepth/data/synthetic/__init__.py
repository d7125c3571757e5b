"""The built-in synthetic street scene: RGB image, dense depth and a simulated LiDAR scan.

No download, runs anywhere: :func:`make_scene` builds a seeded, procedurally generated
street (road with lane markings, raised sidewalks, building façades with windows, parked
and moving cars, poles, street lamps, signs, trees, sky) and renders it by vectorised ray
casting from a pinhole camera:

- ``image``: Lambertian shading from a sun direction, with cast shadows, per-object base
  colours and procedural texture (asphalt noise, lane markings, paving tiles, windows,
  car lights, foliage), a sky gradient with clouds, a mild optical blur (one ray per pixel
  would alias) and a little sensor noise.
- ``depth``: dense ground-truth camera z-depth in metres, **0 where the pixel sees sky**
  (no surface), the same convention as KITTI's ground truth (0 = no value).
- ``sparse``: a simulated Velodyne HDL-64E-like scan (64 beams by default) with range
  noise, random dropouts and a maximum range, mounted like KITTI's LiDAR (0.27 m behind,
  0.08 m above and 0.06 m to the right of the camera) and projected into the camera with
  :func:`crfdepth.geometry.projection.project_to_depth` (z-buffer, nearest point per pixel). Because
  the LiDAR sees the scene from another viewpoint, background points leak through at the
  edges of foreground objects, as they do in KITTI's ``velodyne_raw``.
- ``points``: the same scan as (N, 4) points in the LiDAR frame, with ``T_cam_lidar``.

Coordinate frames (docs/design.md section 1). Camera: x right, y down, z forward
(metres), the camera 1.65 m above a flat ground (KITTI). LiDAR: KITTI Velodyne axes,
x forward, y left, z up. ``T_cam_lidar`` maps homogeneous LiDAR points to camera points:
``p_cam = T @ p_lidar``.

All randomness comes from ``numpy.random.default_rng(seed)``: one seed gives identical
arrays on every run; nothing happens at import.

Modules, one job each:

- :mod:`~crfdepth.data.synthetic.world`: the street as primitives (:func:`~.world.build_world`);
- :mod:`~crfdepth.data.synthetic.raycast`: ray/primitive intersection, nearest hit, normals;
- :mod:`~crfdepth.data.synthetic.texture`: value noise and per-material textures;
- :mod:`~crfdepth.data.synthetic.camera`: intrinsics and the RGB + depth render;
- :mod:`~crfdepth.data.synthetic.lidar_sim`: the spinning LiDAR and its mount;
- :mod:`~crfdepth.data.synthetic.scene`: :func:`make_scene` and :class:`SyntheticScene`;
- :mod:`~crfdepth.data.synthetic.sequence`: :func:`make_sequence`, the street along a
  camera path with true poses and moving cars (:class:`SyntheticSequence`);
- :mod:`~crfdepth.data.synthetic.dataset`: :class:`SyntheticScenes`, a torch Dataset;
- :mod:`~crfdepth.data.synthetic.folder`: scenes written as a KITTI ``val_selection_cropped`` folder;
- :mod:`~crfdepth.data.synthetic.rooms`: indoor rooms at NYU Depth v2's protocol size
  (:func:`~.rooms.make_room`), for learning indoor weights.
"""

from crfdepth.data.synthetic.camera import KITTI_CROP_WIDTH, KITTI_FOCAL_PX, camera_intrinsics
from crfdepth.data.synthetic.dataset import SyntheticScenes
from crfdepth.data.synthetic.folder import selection_stem, write_selection_folder
from crfdepth.data.synthetic.lidar_sim import LIDAR_IN_CAMERA_M, MIN_RANGE_M, lidar_elevations
from crfdepth.data.synthetic.scene import EVAL_MAX_DEPTH_M, SyntheticScene, make_scene
from crfdepth.data.synthetic.sequence import SyntheticFrame, SyntheticSequence, ego_pose, make_sequence
from crfdepth.data.synthetic.world import CAMERA_HEIGHT_M

__all__ = [
    "CAMERA_HEIGHT_M",
    "EVAL_MAX_DEPTH_M",
    "KITTI_CROP_WIDTH",
    "KITTI_FOCAL_PX",
    "LIDAR_IN_CAMERA_M",
    "MIN_RANGE_M",
    "SyntheticFrame",
    "SyntheticScene",
    "SyntheticScenes",
    "SyntheticSequence",
    "camera_intrinsics",
    "ego_pose",
    "lidar_elevations",
    "make_scene",
    "make_sequence",
    "selection_stem",
    "write_selection_folder",
]
