"""One frame of the built-in synthetic street: :func:`make_scene` and :class:`SyntheticScene`.

:func:`make_scene` draws the world (:mod:`~crfdepth.data.synthetic.world`), renders the
camera (:mod:`~crfdepth.data.synthetic.camera`), simulates the LiDAR scan
(:mod:`~crfdepth.data.synthetic.lidar_sim`) and projects it into the image with
:func:`crfdepth.geometry.projection.project_to_depth`. All randomness comes from one
``numpy.random.default_rng(seed)``, drawn in that order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from crfdepth.data.synthetic._checks import check_int, check_real
from crfdepth.data.synthetic.camera import camera_intrinsics, render_camera
from crfdepth.data.synthetic.lidar_sim import MIN_RANGE_M, lidar_to_camera, scan_lidar
from crfdepth.data.synthetic.world import build_world
from crfdepth.geometry.projection import project_to_depth

__all__ = ["EVAL_MAX_DEPTH_M", "SyntheticScene", "make_scene"]

EVAL_MAX_DEPTH_M = 80.0
"""Farthest ground truth used for metrics, metres (KITTI's annotations end near 80 m)."""


@dataclass(frozen=True)
class SyntheticScene:
    """One rendered frame of the synthetic street.

    Attributes:
        image: (H, W, 3) float32 RGB in [0, 1].
        depth: (H, W) float32 dense ground-truth camera z-depth in metres; 0 = sky (no
            surface), like KITTI's ground truth.
        sparse: (H, W) float32 LiDAR z-depth in metres projected into the camera (nearest
            return per pixel); 0 = no LiDAR return.
        K: (3, 3) float64 pinhole intrinsics of ``image`` (pixels).
        points: (N, 4) float32 LiDAR returns in the LiDAR frame (x forward, y left, z up,
            metres) and intensity in [0, 1]; ordered by ring, then azimuth.
        rings: (N,) int64 beam index of each point; 0 = lowest beam (most downward),
            ``beams - 1`` = highest, as in the ROS Velodyne driver.
        T_cam_lidar: (4, 4) float64 rigid transform, LiDAR frame to camera frame.
        name: identifies the frame, e.g. ``"synthetic-seed0"``.
    """

    image: np.ndarray
    depth: np.ndarray
    sparse: np.ndarray
    K: np.ndarray
    points: np.ndarray
    rings: np.ndarray
    T_cam_lidar: np.ndarray
    name: str

    def to_tensors(self) -> dict[str, torch.Tensor]:
        """The frame as torch tensors in the library convention (docs/design.md section 1).

        Returns:
            ``{"image": (3, H, W) float32 in [0, 1], "sparse": (1, H, W) float32 metres
            (0 = no return), "depth": (1, H, W) float32 metres (0 = sky), "K": (3, 3)
            float32 pixels, "target": (1, H, W) float32 metres, :meth:`target`}``. New
            tensors; the scene's arrays are not shared.
        """
        return {
            "image": torch.tensor(self.image.transpose(2, 0, 1), dtype=torch.float32),
            "sparse": torch.tensor(self.sparse[None], dtype=torch.float32),
            "depth": torch.tensor(self.depth[None], dtype=torch.float32),
            "K": torch.tensor(self.K, dtype=torch.float32),
            "target": torch.tensor(self.target()[None], dtype=torch.float32),
        }

    def target(self, max_depth: float = EVAL_MAX_DEPTH_M) -> np.ndarray:
        """(H, W) float32 ground truth restricted like KITTI's: metres, 0 = not evaluated.

        The dense ``depth`` reaches the horizon; KITTI's ground truth (accumulated LiDAR)
        covers only the image below the top scan line and up to about 80 m. Metrics on
        this scene use ``depth`` there: rows below the first row holding a LiDAR return,
        depths in (0, ``max_depth``].
        """
        target = self.depth.copy()
        rows = np.flatnonzero((self.sparse > 0).any(axis=1))
        target[: rows[0] if rows.size else target.shape[0]] = 0.0
        target[target > max_depth] = 0.0
        return target


def check_frame_options(height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout,
                        image_noise_std) -> None:
    """The checks of the camera and LiDAR arguments that :func:`make_scene` and
    :func:`~.sequence.make_sequence` share (ranges in :func:`make_scene`'s docstring)."""
    check_int("height", height, 1, 16384)
    check_int("width", width, 1, 16384)
    check_int("beams", beams, 1, 128)
    check_real("azimuth_step_deg", azimuth_step_deg, 0.0, 10.0, low_open=True)
    check_real("max_range", max_range, MIN_RANGE_M, None, low_open=True)
    check_real("range_noise_std", range_noise_std, 0.0, None)
    check_real("dropout", dropout, 0.0, 1.0, high_open=True)
    check_real("image_noise_std", image_noise_std, 0.0, None)


def render_frame(world, rng, K, T_cam_lidar, height, width, beams, azimuth_step_deg, max_range, range_noise_std,
                 dropout, image_noise_std, pose=None, beam_offsets_deg=None):
    """Render the camera, scan the LiDAR and project the scan into the image: one frame, as
    :func:`make_scene` and :func:`~.sequence.make_sequence` draw it from ``rng`` (in that order).

    ``pose`` and ``beam_offsets_deg`` as in :func:`~.lidar_sim.scan_lidar` (None: the camera
    at the world's origin; offsets drawn from ``rng``); the other options as in :func:`make_scene`.

    Returns:
        ``(image, depth, pixel_index, points, rings, point_index, sparse)``: the arrays of
        :class:`SyntheticScene` and the primitive each pixel (-1: sky) and each point hit.
    """
    image, depth, pixel_index = render_camera(world, K, height, width, rng, float(image_noise_std), pose=pose,
                                              return_index=True)
    points, rings, point_index = scan_lidar(
        world, rng, beams, float(azimuth_step_deg), float(max_range), float(range_noise_std), float(dropout),
        pose=pose, beam_offsets_deg=beam_offsets_deg, return_index=True,
    )
    points_cam = points[:, :3].astype(np.float64) @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
    sparse = project_to_depth(points_cam, K, (height, width))
    return image, depth, pixel_index, points, rings, point_index, sparse


def make_scene(seed: int = 0, height: int = 352, width: int = 1216, beams: int = 64, *, azimuth_step_deg: float = 0.17,
               max_range: float = 100.0, range_noise_std: float = 0.02, dropout: float = 0.03,
               image_noise_std: float = 0.008) -> SyntheticScene:
    """Generate and render one synthetic street frame.

    Args:
        seed: non-negative integer; the same seed gives identical arrays.
        height: image height in pixels, >= 1 (default 352, the KITTI crop).
        width: image width in pixels, >= 1 (default 1216). The focal length scales with
            it (see :func:`camera_intrinsics`).
        beams: number of LiDAR beams, 1 to 128 (64: HDL-64E-like; 32 and 16 sample the
            same vertical field more coarsely, see :func:`lidar_elevations`).
        azimuth_step_deg: horizontal angle between two firings of one beam, degrees, in
            (0, 10]. The scan covers 360 degrees. The default gives 4-5 % of the pixels
            of a 1216x352 frame a return with 64 beams, like KITTI's ``velodyne_raw``.
        max_range: farthest return in metres, > 1 (surfaces beyond give no return).
        range_noise_std: standard deviation of the Gaussian range noise, metres, >= 0.
        dropout: probability that a return is lost, in [0, 1).
        image_noise_std: standard deviation of Gaussian noise added to the RGB image,
            >= 0 (before clipping to [0, 1]).

    Returns:
        A :class:`SyntheticScene`. ``sparse`` is the scan projected with
        :func:`crfdepth.geometry.projection.project_to_depth` using ``T_cam_lidar`` and ``K``.

    Raises:
        InputError: an argument is of the wrong type or out of range.
    """
    check_int("seed", seed, 0, None)
    check_frame_options(height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout,
                        image_noise_std)
    seed, height, width, beams = int(seed), int(height), int(width), int(beams)

    rng = np.random.default_rng(seed)
    world = build_world(rng)
    K = camera_intrinsics(height, width)
    T = lidar_to_camera()
    image, depth, _, points, rings, _, sparse = render_frame(
        world, rng, K, T, height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout, image_noise_std)
    return SyntheticScene(
        image=image, depth=depth, sparse=sparse, K=K, points=points, rings=rings,
        T_cam_lidar=T, name=f"synthetic-seed{seed}",
    )
