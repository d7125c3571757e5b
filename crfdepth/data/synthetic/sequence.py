"""The synthetic street along a camera path: :func:`make_sequence` and :class:`SyntheticSequence`.

The ego car drives through one street of :func:`~.world.build_world` at a constant
``speed`` (m/s), optionally along a gentle curve (a constant ``yaw_rate``), and ``movers``
of the street's cars drive with their own velocities. Every frame is rendered like
:func:`~.scene.make_scene` (RGB image, dense true depth, the simulated LiDAR scan and its
projection) from the frame's true pose (docs/design.md section 12).

How the motion is rendered: the world's primitives are axis-aligned boxes, vertical
cylinders and spheres, which the ray caster cannot turn. The *rays* are moved and turned
instead: each frame's camera and LiDAR rays start at the sensor's position in the world and
point along the sensor's turned axes (a turn about the vertical keeps every box
axis-aligned and the camera's rays separable). Movers are moved by translating their boxes.
Textures are attached to world coordinates, so a static surface looks the same in every
frame (up to shading noise and the sensor noise).

Conventions (KITTI-like):

- **World frame** = the camera frame of frame 0 (x right, y down, z forward, metres); the
  ground is the plane y = 1.65 m.
- ``T_w_cam``: (4, 4) world<-camera, ``p_world = T_w_cam @ p_cam`` (KITTI odometry's
  ``poses.txt`` convention: frame 0 is the identity).
- ``T_w_lidar = T_w_cam @ T_cam_lidar``: world<-LiDAR. The LiDAR is rigidly mounted, so
  the relative LiDAR motion ``T_lidar(0)<-lidar(t) = T_w_lidar(0)^-1 T_w_lidar(t)`` is what
  LiDAR odometry estimates (:meth:`SyntheticSequence.lidar_poses`).
- A positive ``yaw_rate`` turns left (counter-clockwise seen from above, KITTI's yaw about
  the LiDAR's z axis, which points up).
- Scans are instantaneous (no motion during the sweep), as if de-skewed.
- ``stereo_baseline``: an optional second camera, the *right* camera of a rectified pair
  (KITTI's camera 3 beside camera 2): the same intrinsics, the same orientation, moved by the
  baseline along the left camera's x axis (to the right), rendered at the same time as the
  left one. A point at z-depth ``z`` in the left image at column ``u`` is seen in the right
  image at ``u - fx * baseline / z`` (the disparity), on the same row. Its image noise comes
  from a generator of its own, so the rest of the sequence is the same array for array as
  without it (docs/design.md section 16).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from numbers import Real

import numpy as np

from crfdepth.data.synthetic._checks import check_int, check_real
from crfdepth.data.synthetic.camera import camera_intrinsics, render_camera
from crfdepth.data.synthetic.lidar_sim import lidar_to_camera
from crfdepth.data.synthetic.scene import SyntheticScene, check_frame_options, render_frame
from crfdepth.data.synthetic.world import CAR_BODY, World, build_world
from crfdepth.errors import InputError

__all__ = ["SyntheticFrame", "SyntheticSequence", "ego_pose", "make_sequence"]

_CAR_PARTS = 4  # build_world adds a car as body, cabin and two wheel boxes, in this order
_RIGHT_STREAM = 3  # the right camera's noise generator: SeedSequence((seed, frame, 3)), apart from the main one


@dataclass(frozen=True)
class SyntheticFrame(SyntheticScene):
    """One frame of a :class:`SyntheticSequence`: a :class:`SyntheticScene` plus its pose.

    Attributes (beyond :class:`SyntheticScene`'s image, depth, sparse, K, points, rings,
    T_cam_lidar, name):
        index: frame number, 0 first.
        time: seconds since frame 0 (``index / rate``).
        T_w_cam: (4, 4) float64 world<-camera pose (world = frame 0's camera frame).
        T_w_lidar: (4, 4) float64 world<-LiDAR pose, ``T_w_cam @ T_cam_lidar``.
        mover_pixels: (H, W) int16, the mover each pixel sees (index into
            :attr:`SyntheticSequence.mover_velocities`), -1 for static surfaces and sky.
        mover_points: (N,) int16, the mover each LiDAR point hit, -1 for static ones.
        right_image: (H, W, 3) float32 RGB in [0, 1] of the right camera, or None
            (``make_sequence(stereo_baseline=None)``).
        right_depth: (H, W) float32 z-depth in metres seen by the right camera (0 = sky), or None.
        baseline_m: the stereo baseline in metres (the right camera sits at ``x = +baseline_m``
            in the left camera's frame), or None.
    """

    index: int = 0
    time: float = 0.0
    T_w_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_w_lidar: np.ndarray = field(default_factory=lambda: np.eye(4))
    mover_pixels: np.ndarray | None = None
    mover_points: np.ndarray | None = None
    right_image: np.ndarray | None = None
    right_depth: np.ndarray | None = None
    baseline_m: float | None = None

    @property
    def moving_pixels(self) -> np.ndarray:
        """(H, W) bool: the pixel sees a moving object."""
        return self.mover_pixels >= 0

    @property
    def moving_points(self) -> np.ndarray:
        """(N,) bool: the LiDAR point lies on a moving object."""
        return self.mover_points >= 0


@dataclass(frozen=True)
class SyntheticSequence:
    """A rendered drive through the synthetic street (see the module docstring).

    Attributes:
        frames: the :class:`SyntheticFrame` s in time order.
        rate: frames per second.
        speed: the ego car's speed along its path, m/s.
        yaw_rate: the ego car's yaw rate, degrees per second (positive: left turn).
        world: the street at time 0 (movers at their start).
        mover_parts: (M, 4) int64 primitive indices (body, cabin, wheels) of each mover.
        mover_velocities: (M, 3) float64 world-frame velocity of each mover, m/s.
        seed: the seed it was drawn from.
    """

    frames: list[SyntheticFrame]
    rate: float
    speed: float
    yaw_rate: float
    world: World
    mover_parts: np.ndarray
    mover_velocities: np.ndarray
    seed: int

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> SyntheticFrame:
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    @property
    def T_cam_lidar(self) -> np.ndarray:
        """(4, 4) LiDAR-to-camera extrinsic (the same in every frame)."""
        return self.frames[0].T_cam_lidar

    def camera_poses(self) -> np.ndarray:
        """(n, 4, 4) world<-camera poses ``T_w_cam`` (the first is the identity)."""
        return np.stack([f.T_w_cam for f in self.frames])

    def lidar_poses(self) -> np.ndarray:
        """(n, 4, 4) ``T_lidar(0)<-lidar(t)``: LiDAR poses relative to the first scan (the
        first is the identity), what LiDAR odometry returns."""
        first = np.linalg.inv(self.frames[0].T_w_lidar)
        return np.stack([first @ f.T_w_lidar for f in self.frames])

    def world_at(self, time: float) -> World:
        """The street at ``time`` seconds: the movers' boxes moved by their velocities."""
        return _world_at(self.world, self.mover_parts, self.mover_velocities, time)


def ego_pose(time: float, speed: float, yaw_rate_deg: float) -> np.ndarray:
    """(4, 4) world<-camera pose of the ego camera at ``time`` (exact integration).

    The camera starts at the world's origin looking along z and moves at ``speed`` m/s
    along its heading, which turns at ``yaw_rate_deg`` degrees/s (positive: left, i.e.
    towards -x). On a curve the camera follows a circle of radius ``speed / yaw_rate``.
    """
    w = math.radians(yaw_rate_deg)
    th = w * time
    c, s = math.cos(th), math.sin(th)
    T = np.eye(4)
    # Heading th to the left = a turn by -th about the camera's y axis (which points down).
    T[:3, :3] = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]
    if abs(w) < 1e-12:
        T[2, 3] = speed * time
    else:
        T[0, 3] = speed * (c - 1.0) / w
        T[2, 3] = speed * s / w
    return T


def _world_at(world: World, parts: np.ndarray, velocities: np.ndarray, time: float) -> World:
    if len(parts) == 0:
        return world
    lo, hi = world.lo.copy(), world.hi.copy()
    for idx, v in zip(parts, velocities):
        lo[idx] += v * time
        hi[idx] += v * time
    return dataclasses.replace(world, lo=lo, hi=hi)


def _cars(world: World) -> np.ndarray:
    """(C, 4) primitive indices of the street's cars, those in the driving lanes first
    (nearest first), then the parked ones (nearest first)."""
    bodies = np.flatnonzero(world.mat == CAR_BODY)
    cx = 0.5 * (world.lo[bodies, 0] + world.hi[bodies, 0])
    z0 = world.lo[bodies, 2]
    in_lane = (cx > world.road["line_l"]) & (cx < world.road["line_r"])
    order = np.lexsort((np.abs(z0), ~in_lane))
    return bodies[order][:, None] + np.arange(_CAR_PARTS)[None, :]


def _mover_velocities(movers, n_cars: int, speed: float, rng) -> np.ndarray:
    if isinstance(movers, bool):
        raise InputError(f"movers: expected an integer or a list of velocities, got {movers!r}")
    if isinstance(movers, (int, np.integer)):
        check_int("movers", int(movers), 0, n_cars)
        n = int(movers)
        v = np.zeros((n, 3))
        # Traffic in the ego car's direction, a little slower or faster than it.
        v[:, 2] = speed + rng.uniform(-2.0, 4.0, n)
        return v
    try:
        items = list(movers)
    except TypeError:
        raise InputError(f"movers: expected an integer or a list of velocities, got {movers!r}") from None
    if len(items) > n_cars:
        raise InputError(f"movers: expected at most {n_cars} velocities (the street's cars), got {len(items)}")
    v = np.zeros((len(items), 3))
    for k, item in enumerate(items):
        if isinstance(item, Real) and not isinstance(item, bool):
            v[k, 2] = float(item)  # forward speed along the street
        else:
            a = np.asarray(item, dtype=np.float64) if not isinstance(item, str) else np.zeros(0)
            if a.shape != (3,):
                raise InputError(
                    f"movers[{k}]: expected a speed along the street (m/s) or a 3-vector "
                    f"(x right, y down, z forward, m/s), got {item!r}")
            v[k] = a
        if not np.isfinite(v[k]).all():
            raise InputError(f"movers[{k}]: expected finite velocities, got {item!r}")
    return v


def _render_right(world: World, K, height: int, width: int, image_noise_std: float, T_w_cam: np.ndarray,
                  baseline: float, seed: int, index: int) -> dict:
    """The right camera of frame ``index``: ``T_w_cam`` moved by ``baseline`` along its x axis, its
    image noise drawn from a generator seeded by (seed, index) alone, so that the left camera's and
    the LiDAR's draws are untouched."""
    shift = np.eye(4)
    shift[0, 3] = baseline
    rng = np.random.default_rng((seed, index, _RIGHT_STREAM))
    image, depth = render_camera(world, K, height, width, rng, float(image_noise_std), pose=T_w_cam @ shift)
    return {"right_image": image, "right_depth": depth, "baseline_m": baseline}


def make_sequence(n_frames: int = 10, seed: int = 0, *, speed: float = 10.0, rate: float = 10.0, yaw_rate: float = 0.0,
                  movers=0, height: int = 352, width: int = 1216, beams: int = 64, azimuth_step_deg: float = 0.17,
                  max_range: float = 100.0, range_noise_std: float = 0.02, dropout: float = 0.03,
                  image_noise_std: float = 0.008, stereo_baseline: float | None = None) -> SyntheticSequence:
    """Render the synthetic street along the ego car's path.

    Args:
        n_frames: number of frames, 1 to 10000.
        seed: non-negative integer; the same arguments give identical arrays. The street
            is the one :func:`~.scene.make_scene` draws for this seed.
        speed: the ego car's speed, m/s, in [0, 60].
        rate: frames (and scans) per second, in (0, 1000]; default 10 Hz (KITTI).
        yaw_rate: degrees per second, in [-90, 90]; positive turns left. The street stays
            straight: keep ``|yaw_rate| * duration`` small (a few degrees).
        movers: how many of the street's cars move (an integer; cars in the driving lanes
            first, nearest first, then parked ones), each along the street at the ego speed
            plus a random -2 to +4 m/s; or a list of velocities, one per mover, each a
            speed along the street (m/s) or a 3-vector in the world frame (m/s).
        height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout,
        image_noise_std: as in :func:`~.scene.make_scene`, per frame.
        stereo_baseline: None (default: one camera), or the baseline in metres, in (0, 10],
            of a right camera rendered beside the left one in every frame (module docstring;
            KITTI's is 0.54 m). Every other array is the same as without it.

    Returns:
        A :class:`SyntheticSequence`. Per frame the image and LiDAR noise, the dropouts and
        the scan's start azimuth are drawn anew; the beams' elevation errors are drawn once
        (one sensor).

    Raises:
        InputError: an argument is of the wrong type or out of range.
    """
    check_int("n_frames", n_frames, 1, 10000)
    check_int("seed", seed, 0, None)
    check_real("speed", speed, 0.0, 60.0)
    check_real("rate", rate, 0.0, 1000.0, low_open=True)
    check_real("yaw_rate", yaw_rate, -90.0, 90.0)
    check_frame_options(height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout,
                        image_noise_std)
    if stereo_baseline is not None:
        check_real("stereo_baseline", stereo_baseline, 0.0, 10.0, low_open=True)
    n_frames, seed, height, width, beams = int(n_frames), int(seed), int(height), int(width), int(beams)
    speed, rate, yaw_rate = float(speed), float(rate), float(yaw_rate)

    rng = np.random.default_rng(seed)
    world0 = build_world(rng)
    cars = _cars(world0)
    velocities = _mover_velocities(movers, len(cars), speed, rng)
    parts = cars[: len(velocities)]
    beam_offsets = rng.normal(0.0, 0.02, beams)
    K = camera_intrinsics(height, width)
    T_cam_lidar = lidar_to_camera()
    # Primitive index -> mover index (-1: static; the last entry serves idx = -1, sky).
    owner = np.full(len(world0.kind) + 1, -1, dtype=np.int16)
    for m, idx in enumerate(parts):
        owner[idx] = m

    frames = []
    for k in range(n_frames):
        t = k / rate
        world = _world_at(world0, parts, velocities, t)
        T_w_cam = ego_pose(t, speed, yaw_rate)
        image, depth, pix_idx, points, rings, pt_idx, sparse = render_frame(
            world, rng, K, T_cam_lidar, height, width, beams, azimuth_step_deg, max_range, range_noise_std, dropout,
            image_noise_std, pose=T_w_cam, beam_offsets_deg=beam_offsets)
        right = {}
        if stereo_baseline is not None:
            right = _render_right(world, K, height, width, image_noise_std, T_w_cam, float(stereo_baseline), seed, k)
        frames.append(SyntheticFrame(
            image=image, depth=depth, sparse=sparse, K=K, points=points, rings=rings,
            T_cam_lidar=T_cam_lidar, name=f"synthetic-seed{seed}-frame{k:04d}",
            index=k, time=t, T_w_cam=T_w_cam, T_w_lidar=T_w_cam @ T_cam_lidar,
            mover_pixels=owner[pix_idx], mover_points=owner[pt_idx], **right,
        ))
    return SyntheticSequence(
        frames=frames, rate=rate, speed=speed, yaw_rate=yaw_rate, world=world0,
        mover_parts=parts, mover_velocities=velocities, seed=seed,
    )
