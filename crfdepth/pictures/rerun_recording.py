"""A Rerun recording of completed frames: what ``--rerun`` of ``crfdepth demo``, ``complete`` and ``targets``
writes (rerun-sdk, the optional extra ``pip install 'crfdepth[viewer]'``; ``rerun`` is imported only when a
recording is made, :func:`import_rerun`).

Every frame is one time step of the sequence timeline ``frame`` (0, 1, ... in the order the frames are
completed; a ROS bag's frames also on the timeline ``stamp``, the image's header stamp). Entity paths:

- ``world``: static view coordinates RDF (x right, y down, z forward: the camera frame of docs/design.md
  section 1), so that the 3D view shows the scene upright for a level camera;
- ``world/camera``: ``rr.Transform3D``, the camera's pose in the world ``T_world_cam`` (rotation
  ``mat3x3`` and ``translation``, metres). ``complete`` and ``demo`` know no poses: every frame is seen in its
  own camera, the identity. ``targets`` logs the drive's poses, the world being the camera at the first scan
  the run uses;
- ``world/camera/image``: ``rr.Pinhole`` (``image_from_camera`` = K, ``resolution`` = (W, H)) and ``rr.Image``,
  the RGB image the model saw (undistorted, as :func:`crfdepth.api.complete_depth` does, when the calibration
  has lens distortion);
- ``world/camera/image/lidar``: ``rr.Points2D``, the LiDAR points in front of the camera and inside the
  image, at their pixels ``K x / z``, coloured by depth (TURBO on inverse depth, near = red, as
  :func:`crfdepth.pictures.colour.colorize_depth`, over the 2nd to 98th percentile of the frame's points);
- ``world/camera/image/depth``: ``rr.DepthImage``, the dense depth, float32 metres, ``meter=1``; under the
  pinhole, so the viewer lifts it into 3D;
- ``world/camera/image/targets``: ``rr.DepthImage``, the camera-view targets (``targets``), float32 metres,
  0 = no target;
- ``world/lidar``: ``rr.Points3D``, the LiDAR points in the world frame, coloured as on the image: the
  pixels of a sparse depth map back-projected with K (:func:`sparse_points`), or every point of a raw cloud
  (``--points``, a bag, a drive's scan) moved into the camera by ``T_cam_lidar``;
- ``world/trajectory``: ``rr.LineStrips3D``, the camera positions of the frames so far (``targets``);
- ``std``: ``rr.DepthImage``, the predictive standard deviation (docs/design.md section 5), float32 metres,
  ``meter=1``, VIRIDIS. A DepthImage keeps the metres (the viewer shows a pixel's std on hover) where a
  coloured picture would keep colours only; it is logged outside the pinhole's subtree because the viewer
  lifts every DepthImage under a pinhole into 3D, and a std is not a distance from the camera.

An entity without a value is left out: ``std`` without a std asked for, ``depth`` in ``targets``,
``targets`` and ``world/trajectory`` in ``complete`` and ``demo``.

Rerun puts a pixel's centre at ``+0.5`` where KITTI and OpenCV put it at the integer coordinate; the
pinhole holds K as given, so everything the viewer draws sits half a pixel up and left of the pixel's
centre, consistently for the image, the points and the lifted depth.

:func:`open_recording` writes a ``.rrd`` file atomically (a temporary file beside it, renamed at the end,
removed on an error: no partial recording is left) or streams to a viewer; :func:`log_frame` logs one frame
into any ``rerun.RecordingStream``; :class:`Recorder` numbers the frames of a command.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import secrets
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from crfdepth.errors import InputError
from crfdepth.io.calibration import RigCalibration
from crfdepth.pictures.colour import colorize_depth

if TYPE_CHECKING:
    import rerun

__all__ = ["CAMERA", "DEPTH", "IMAGE", "LIDAR_2D", "LIDAR_3D", "STD", "TARGETS", "TRAJECTORY", "WORLD",
           "Recorder", "import_rerun", "log_frame", "open_recording", "project", "sparse_points"]

WORLD = "world"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
LIDAR_2D = "world/camera/image/lidar"
DEPTH = "world/camera/image/depth"
TARGETS = "world/camera/image/targets"
LIDAR_3D = "world/lidar"
TRAJECTORY = "world/trajectory"
STD = "std"
VIEWER_EXTRA = "pip install 'crfdepth[viewer]'"


def import_rerun(name: str = "rerun"):
    """The ``rerun`` module; InputError naming ``name`` (the caller's flag, ``--rerun``) when rerun-sdk is not
    installed."""
    try:
        return importlib.import_module("rerun")
    except ImportError:
        raise InputError(f"{name}: needs the viewer extra: {VIEWER_EXTRA} (rerun-sdk), got no module rerun") from None


@contextlib.contextmanager
def open_recording(path: str | os.PathLike | None, *, name: str = "path",
                   application_id: str = "crfdepth") -> Iterator[rerun.RecordingStream]:
    """A new ``rerun.RecordingStream`` for the ``with`` block, saved to ``path`` (a ``.rrd`` file) or, with
    ``path`` None, sent to a Rerun viewer: the one listening on its default port, else one spawned.

    The file is written to a temporary file beside ``path`` (``.<name>.<random>.tmp``) and renamed over
    ``path`` when the block ends; when the block raises (Ctrl-C included) the temporary file is removed, so
    no partial recording is ever left. The caller checks ``path`` first
    (:func:`crfdepth.io.files.check_output_file`). ``name`` names the argument in errors: rerun-sdk missing
    (InputError), a viewer that could not be reached (``ConnectionError``, when the block ends).
    """
    rr = import_rerun(name)
    stream = rr.RecordingStream(application_id, recording_id=uuid.uuid4())
    if path is None:
        stream.spawn()  # a viewer that fails to start (no display) is only known when the data cannot be sent
        yield stream
        try:
            stream.flush()
        except RuntimeError as exc:
            raise ConnectionError(f"{name}: cannot stream to a Rerun viewer ({exc}); save to a .rrd file "
                                  f"instead") from None
        return
    target = Path(path)
    temporary = target.parent / f".{target.name}.{secrets.token_hex(6)}.tmp"
    try:
        stream.save(temporary)
        yield stream
        stream.flush()
        stream.disconnect()  # closes the file: the recording is complete
        os.replace(temporary, target)
    except BaseException:
        stream.disconnect()
        temporary.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- geometry


def _numpy(values, dtype=np.float64) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=dtype)


def _map(name: str, values) -> np.ndarray:
    """(H, W) float32 of a map in metres (numpy or torch; leading singleton dims dropped)."""
    array = _numpy(values, np.float32)
    while array.ndim > 2 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 2:
        raise InputError(f"{name}: expected an (H, W) map in metres, got shape {tuple(np.shape(values))}")
    return array


def _rgb(image) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an (H, W, 3) uint8 image or a (3, H, W) float image in [0, 1] (numpy or torch)."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[0] == 3 and image.shape[2] != 3:  # (3, H, W)
        image = image.transpose(1, 2, 0)
    if image.dtype != np.uint8:  # [0, 1]
        image = np.round(np.clip(image.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"image: expected (H, W, 3) uint8 RGB or (3, H, W) in [0, 1], got shape {image.shape}")
    return image


def sparse_points(sparse, K) -> np.ndarray:
    """The pixels of a sparse depth map back-projected into the camera: ``z K^-1 (u, v, 1)``.

    Args:
        sparse: (H, W) z-depth in metres, 0 = no LiDAR point (numpy or torch; (1, H, W) too).
        K: (3, 3) pinhole intrinsics, pixels; pixel (row v, column u) is at ``(u, v)``.

    Returns:
        (N, 3) float64 points in the camera frame (x right, y down, z forward), metres, one per pixel
        with a depth > 0, in row-major order. :func:`project` maps them back onto their pixels.
    """
    depth = _map("sparse", sparse).astype(np.float64)
    K = _numpy(K)
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u]
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1)


def project(points_cam: np.ndarray, K, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(u, v) = (K x / z)[:2]`` of the points in front of the camera (z > 0) that land inside the
    image of ``size`` (H, W), as an (M, 2) float array, and their z-depths (M,) in metres."""
    K = _numpy(K)
    points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    front = points[:, 2] > 0
    uvw = points[front] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    height, width = size
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)
    return uv[inside], points[front][inside, 2]


def _colours(z: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 TURBO colours of z-depths (metres; <= 0 black) over their 2nd to 98th percentile."""
    valid = z[np.isfinite(z) & (z > 0)]
    if valid.size == 0:
        return np.zeros((len(z), 3), np.uint8)
    low, high = np.percentile(valid, [2.0, 98.0])
    return colorize_depth(z[None, :], vmin=float(low), vmax=float(max(high, low)))[0]


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- logging


def log_frame(stream: rerun.RecordingStream, frame: int, *, image, K, points_cam: np.ndarray,
              T_world_cam: np.ndarray | None = None, depth=None, std=None, targets=None,
              trajectory: np.ndarray | None = None, stamp_ns: int | None = None) -> None:
    """Log one frame at time step ``frame`` of the timeline ``frame`` (entity paths: the module docstring).

    Args:
        stream: the ``rerun.RecordingStream`` to log into (:func:`open_recording`).
        frame: the time step, >= 0.
        image: (H, W, 3) uint8 RGB, or (3, H, W) float in [0, 1] (numpy or torch).
        K: (3, 3) pinhole intrinsics of ``image``, pixels.
        points_cam: (N, 3) LiDAR points in the camera frame, metres (:func:`sparse_points` of a sparse map, or
            a cloud moved by ``T_cam_lidar``); those behind the camera or outside the image are drawn in 3D only.
        T_world_cam: (4, 4) camera pose in the world; None = the identity (the world is this camera).
        depth, std, targets: (H, W) maps in metres or None (then not logged): the dense depth, its standard
            deviation and camera-view targets (0 = none).
        trajectory: (T, 3) camera positions in the world up to this frame, or None.
        stamp_ns: the frame's time in nanoseconds since the epoch (timeline ``stamp``), or None.
    """
    rr = import_rerun()
    rgb = _rgb(image)
    size = rgb.shape[:2]
    K = _numpy(K)
    if K.shape != (3, 3):
        raise InputError(f"K: expected a (3, 3) matrix, got shape {K.shape}")
    pose = np.eye(4) if T_world_cam is None else _numpy(T_world_cam)
    maps = {entity: _map(label, values) for entity, label, values in
            ((DEPTH, "depth", depth), (STD, "std", std), (TARGETS, "targets", targets)) if values is not None}
    for entity, values in maps.items():
        if values.shape != size:
            raise InputError(f"{entity.rsplit('/', 1)[-1]}: expected the image's size {size[0]}x{size[1]} (HxW), "
                             f"got {values.shape[0]}x{values.shape[1]}")
    points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    stream.set_time("frame", sequence=int(frame))
    if stamp_ns is not None:
        stream.set_time("stamp", timestamp=np.datetime64(int(stamp_ns), "ns"))
    stream.log(WORLD, rr.ViewCoordinates.RDF, static=True)
    stream.log(CAMERA, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
    stream.log(IMAGE, rr.Pinhole(image_from_camera=K, resolution=[size[1], size[0]]))
    stream.log(IMAGE, rr.Image(rgb, color_model="RGB"))
    uv, z = project(points, K, size)
    stream.log(LIDAR_2D, rr.Points2D(uv, colors=_colours(z)))
    stream.log(LIDAR_3D, rr.Points3D(_transform(pose, points), colors=_colours(points[:, 2])))
    for entity, values in maps.items():
        extra = {"colormap": "viridis"} if entity == STD else {}
        stream.log(entity, rr.DepthImage(values, meter=1.0, **extra))
    if trajectory is not None:
        stream.log(TRAJECTORY, rr.LineStrips3D([np.asarray(trajectory, dtype=np.float64).reshape(-1, 3)]))


class Recorder:
    """The frames of one command logged into ``stream``, one time step each in the order they come
    (:func:`log_frame`); the CLI's ``--rerun`` holds one (``crfdepth.cli.outputs.rerun_recording``)."""

    def __init__(self, stream: rerun.RecordingStream) -> None:
        self.stream = stream
        self.frames = 0
        self._positions: list[np.ndarray] = []

    def complete_frame(self, image, depth, std=None, *, sparse=None, K=None, points=None,
                       calibration: RigCalibration | None = None, stamp_ns: int | None = None) -> None:
        """A completed frame, in its own camera (no pose): ``image`` with ``sparse`` + ``K``, or with the raw
        LiDAR ``points`` ((N, 3+) metres, LiDAR frame) + ``calibration`` (its image undistorted when it has
        distortion); ``depth`` and ``std`` (None: not logged) as :func:`log_frame` takes them."""
        if points is not None:
            rgb = _rgb(image)
            if calibration.distortion is not None:
                rgb = cv2.undistort(rgb, calibration.K, calibration.distortion)
            lidar = _transform(calibration.T_cam_lidar, _numpy(points)[:, :3])
            image, K = rgb, calibration.K
        else:
            lidar = sparse_points(sparse, K)
        log_frame(self.stream, self.frames, image=image, K=K, points_cam=lidar, depth=depth, std=std,
                  stamp_ns=stamp_ns)
        self.frames += 1

    def targets_frame(self, image, targets, *, scan: np.ndarray, calibration: RigCalibration,
                      pose: np.ndarray) -> None:
        """A frame of ``crfdepth targets``: the frame's own ``scan`` ((N, 3+) metres, LiDAR frame) and its
        camera-view ``targets`` ((H, W) metres, 0 = none), at ``pose`` ``T_lidar(first)<-lidar(t)`` (the world
        is the camera at the first scan), the trajectory growing by the camera's position."""
        T = calibration.T_cam_lidar
        T_world_cam = T @ _numpy(pose) @ np.linalg.inv(T)
        self._positions.append(T_world_cam[:3, 3])
        log_frame(self.stream, self.frames, image=image, K=calibration.K,
                  points_cam=_transform(T, _numpy(scan)[:, :3]), T_world_cam=T_world_cam, targets=targets,
                  trajectory=np.stack(self._positions))
        self.frames += 1
