"""Numbers that make no sense are refused, not solved: LiDAR returns nearer than 1 mm or beyond 1000 m
(crfdepth.checks.check_return_depths) in a sparse map given to the API or the CLI or projected from points,
depths a KITTI PNG cannot hold (never clipped by ``crfdepth project``), a scan landing no point in the image,
and meta tensors (a shape without values) given as image, sparse, K or points. Oracle: the docs/example rig
(a 640x480 frame whose projected scan has a median of 7.2 m) and the real KITTI raw frame."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth import api
from crfdepth.checks import MAX_RETURN_DEPTH_M, MIN_RETURN_DEPTH_M, check_return_depths
from crfdepth.cli import main
from crfdepth.errors import InputError
from crfdepth.inputs import points_to_sparse
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.kitti import MAX_PNG_DEPTH_M, check_png_depth, read_rgb, read_velodyne, write_depth_png
from crfdepth.io.pointcloud import read_points
from crfdepth.model import CRFDepth

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "example"
DRIVE = "raw/2011_09_26/2011_09_26_drive_0001_sync"
RANGE = "expected LiDAR depths from 0.001 to 1000 m (0 = no return), got "


@pytest.fixture(scope="module")
def example():
    rig = load_any_calibration(EXAMPLE / "rig.yaml")
    points = read_points(EXAMPLE / "scan.pcd")
    return {"rig": rig, "points": points, "rgb": read_rgb(EXAMPLE / "image.png"),
            "sparse": points_to_sparse(points, rig, (480, 640))}


def _one_return(sparse: np.ndarray, value: float) -> np.ndarray:
    """``sparse`` with its first return set to ``value`` metres."""
    out = sparse.copy()
    row, col = np.argwhere(out > 0)[0]
    out[row, col] = value
    return out


def _camera_points(rig, xyz_cam: np.ndarray) -> np.ndarray:
    """Camera-frame points (x right, y down, z forward) as LiDAR points of ``rig``."""
    T = np.linalg.inv(rig.T_cam_lidar)
    return xyz_cam @ T[:3, :3].T + T[:3, 3]


def test_bounds_are_a_millimetre_and_a_kilometre():
    assert (MIN_RETURN_DEPTH_M, MAX_RETURN_DEPTH_M) == (1e-3, 1000.0)
    check_return_depths("sparse", np.array([[0.0, 1e-3, 1000.0]]))  # inclusive, 0 = no return
    check_return_depths("sparse", torch.tensor([[0.0, 1e-3, 1000.0]]))


@pytest.mark.parametrize("value, got", [(5000.0, "1 beyond 1000 m (largest 5000 m)"),
                                        (1e-5, "1 below 0.001 m (smallest 1e-05 m)")])
def test_complete_depth_refuses_a_sparse_return_out_of_range(example, value, got):
    sparse = _one_return(example["sparse"], value)
    expected = f"^sparse: {RANGE}{got}: another unit, or not measured depth$".replace("(", r"\(").replace(")", r"\)")
    with pytest.raises(InputError, match=expected):
        api.complete_depth(example["rgb"], sparse=sparse, K=example["rig"].K, model=CRFDepth(mode="pixel"))
    with pytest.raises(InputError, match=expected):
        api.check_frame(example["rgb"], sparse, example["rig"].K)


def test_returns_at_the_bounds_are_accepted(example):
    sparse = _one_return(_one_return(example["sparse"], MAX_RETURN_DEPTH_M)[::-1], MIN_RETURN_DEPTH_M)[::-1]
    api.check_frame(example["rgb"], np.ascontiguousarray(sparse), example["rig"].K)


@pytest.mark.parametrize("call", ["forward", "complete_batch"])
@pytest.mark.parametrize("value, got", [(5000.0, "1 beyond 1000 m"), (1e-4, "1 below 0.001 m")])
def test_model_and_batch_refuse_a_sparse_return_out_of_range(example, call, value, got):
    image = torch.from_numpy(example["rgb"]).permute(2, 0, 1)[None].float() / 255
    sparse = torch.from_numpy(_one_return(example["sparse"], value))[None, None]
    K = torch.from_numpy(example["rig"].K).float()
    model = CRFDepth(mode="pixel")
    with pytest.raises(InputError, match=f"^sparse: {RANGE.replace('(', '[(]').replace(')', '[)]')}{got}"):
        model(image, sparse, K) if call == "forward" else api.complete_batch(image, sparse, K, model=model)


def test_points_projected_beyond_a_kilometre_are_refused(example):
    rig = example["rig"]
    far = _camera_points(rig, np.array([[x, 0.0, 2000.0] for x in range(-200, 201, 20)]))
    points = np.vstack([example["points"][:, :3], far])
    with pytest.raises(InputError, match=r"^points: expected LiDAR depths from 0\.001 to 1000 m \(0 = no return\), "
                                         r"got \d+ beyond 1000 m \(largest 2000 m\)"):
        api.complete_depth(example["rgb"], points=points, calibration=rig, model=CRFDepth(mode="pixel"))


def test_points_projected_nearer_than_a_millimetre_are_refused(example):
    rig = example["rig"]
    near = _camera_points(rig, np.array([[0.0, 0.0, 5e-4]]))  # on the optical axis: lands at (cx, cy), nearest
    points = np.vstack([example["points"][:, :3], near])
    with pytest.raises(InputError, match=r"^points: expected LiDAR depths .* got 1 below 0\.001 m \(smallest 0\.0005 m"):
        points_to_sparse(points, rig, (480, 640))


# --------------------------------------------------------------------------- the CLI


def _first_error(capsys, argv, out: Path) -> str:
    assert main(argv) == 2
    first = capsys.readouterr().err.splitlines()[0]
    assert not out.exists()
    return first


def test_cli_sparse_png_beyond_a_kilometre_is_refused(capsys, tmp_path, example):
    """A PNG of whole metres (--sparse-units m) can hold 65535 m: a return at 5000 m is refused, naming --sparse."""
    png, k_path, out = tmp_path / "sparse.png", tmp_path / "K.txt", tmp_path / "out.png"
    cv2.imwrite(str(png), np.round(_one_return(example["sparse"], 5000.0)).astype(np.uint16))
    k_path.write_text(" ".join(f"{v:.6f}" for v in example["rig"].K.ravel()))
    first = _first_error(capsys, ["complete", "--image", str(EXAMPLE / "image.png"), "--sparse", str(png),
                                  "--sparse-units", "m", "--intrinsics", str(k_path), "--out", str(out)], out)
    assert first == f"crfdepth complete: error: --sparse {png}: {RANGE}1 beyond 1000 m (largest 5000 m): another " \
                    f"unit, or not measured depth"


def test_cli_points_projected_beyond_a_kilometre_are_refused(capsys, tmp_path, example):
    rig = example["rig"]
    cloud, out = tmp_path / "cloud.npy", tmp_path / "out.png"
    np.save(cloud, np.vstack([example["points"][:, :3], _camera_points(rig, np.array([[0.0, -50.0, 3000.0]]))]))
    first = _first_error(capsys, ["complete", "--image", str(EXAMPLE / "image.png"), "--points", str(cloud), "--calib",
                                  str(EXAMPLE / "rig.yaml"), "--out", str(out)], out)
    assert first.startswith(f"crfdepth complete: error: --points {cloud}: {RANGE}1 beyond 1000 m (largest 3000 m)")


def _moved(points: np.ndarray, distance: float, count: int = 20) -> np.ndarray:
    """``points`` with ``count`` returns well inside the camera's view moved along their ray to ``distance`` m."""
    out = points.copy()
    x, y, z = out[:, 0], out[:, 1], out[:, 2]
    ahead = np.flatnonzero((x > 10) & (np.abs(y) < 0.2 * x) & (np.abs(z) < 0.05 * x))
    chosen = ahead[:: len(ahead) // count][:count]
    out[chosen, :3] *= distance / np.linalg.norm(out[chosen, :3], axis=1, keepdims=True)
    return out


def _project(kitti_root, scan: Path, out: Path) -> list[str]:
    return ["project", "--velodyne", str(scan), "--calib", str(kitti_root / "raw/2011_09_26"), "--image",
            str(kitti_root / DRIVE / "image_02/data/0000000005.png"), "--out", str(out)]


@pytest.fixture
def real_scan(kitti_root) -> np.ndarray:
    return read_velodyne(kitti_root / DRIVE / "velodyne_points/data/0000000005.bin")


@pytest.mark.kitti
def test_project_refuses_returns_beyond_a_kilometre(capsys, tmp_path, kitti_root, real_scan):
    scan, out = tmp_path / "scan.bin", tmp_path / "out.png"
    _moved(real_scan, 2000.0).tofile(scan)
    first = _first_error(capsys, _project(kitti_root, scan, out), out)
    assert first.startswith(f"crfdepth project: error: --velodyne: {RANGE}")
    assert re.search(r"got \d+ beyond 1000 m \(largest 199\d m\)", first), first  # z-depth of a 2000 m range


@pytest.mark.kitti
def test_project_refuses_depths_beyond_the_png_range_instead_of_clipping(capsys, tmp_path, kitti_root, real_scan):
    scan, out = tmp_path / "scan.bin", tmp_path / "out.png"
    _moved(real_scan, 300.0).tofile(scan)
    first = _first_error(capsys, _project(kitti_root, scan, out), out)
    assert first.startswith("crfdepth project: error: --velodyne: expected depths a KITTI depth PNG holds (16 bits, "
                            "metres * 256: at most 255.996 m), got ")
    assert first.endswith("refusing to clip them")


@pytest.mark.kitti
def test_project_refuses_a_scan_that_lands_no_point(capsys, tmp_path, kitti_root, real_scan):
    """Only the returns behind the car: nothing in the camera's view, no all-zero PNG."""
    scan, out = tmp_path / "scan.bin", tmp_path / "out.png"
    real_scan[real_scan[:, 0] < -5].tofile(scan)
    first = _first_error(capsys, _project(kitti_root, scan, out), out)
    assert first.startswith("crfdepth project: error: --velodyne: no point lands in the 1242x375 (WxH) image: ")


@pytest.mark.kitti
def test_project_still_writes_a_valid_scan(capsys, tmp_path, kitti_root):
    out = tmp_path / "out.png"
    assert main(_project(kitti_root, kitti_root / DRIVE / "velodyne_points/data/0000000005.bin", out)) == 0
    assert capsys.readouterr().out == f"wrote {out}: 19137 LiDAR pixels, 375x1242\n"


def test_png_range_check_and_the_writers_warning(tmp_path, caplog):
    check_png_depth("--velodyne", np.array([[0.0, MAX_PNG_DEPTH_M]]))
    with pytest.raises(InputError, match=r"^--velodyne: expected depths a KITTI depth PNG holds .* got 1 pixel\(s\) "
                                         r"beyond, up to 300 m; refusing to clip them$"):
        check_png_depth("--velodyne", np.array([[0.0, 300.0]]))
    with caplog.at_level(logging.WARNING, logger="crfdepth.io.kitti"):
        write_depth_png(tmp_path / "d.png", np.array([[0.0, 300.0]]))  # the writer clips, saying so
    assert "1 depth value(s) beyond 255.996 m (up to 300 m) clipped" in caplog.text


# --------------------------------------------------------------------------- meta tensors


def _meta(shape) -> torch.Tensor:
    return torch.empty(shape, device="meta")


META = r"^{}: expected a tensor holding values \(on cpu, cuda or mps\), got a meta tensor \(shape {} float32, " \
       r"device 'meta': a shape without data\)$"


@pytest.mark.parametrize("name", ["image", "sparse", "K"])
def test_model_forward_names_a_meta_tensor(name):
    frame = {"image": torch.rand(1, 3, 8, 8), "sparse": torch.zeros(1, 1, 8, 8),
             "K": torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]])}
    frame["sparse"][0, 0, 2, 2] = 5.0
    frame[name] = _meta(frame[name].shape)
    shape = str(tuple(frame[name].shape)).replace("(", r"\(").replace(")", r"\)")
    with pytest.raises(InputError, match=META.format(name, shape)):
        CRFDepth(mode="pixel")(frame["image"], frame["sparse"], frame["K"])


@pytest.mark.parametrize("name", ["image", "sparse", "points"])
def test_complete_depth_and_check_frame_name_a_meta_tensor(example, name):
    frame = {"image": torch.from_numpy(example["rgb"]).float() / 255, "sparse": torch.from_numpy(example["sparse"]),
             "points": torch.from_numpy(example["points"])}
    frame[name] = _meta(frame[name].shape)
    shape = str(tuple(frame[name].shape)).replace("(", r"\(").replace(")", r"\)")
    rig, model = example["rig"], CRFDepth(mode="pixel")
    with pytest.raises(InputError, match=META.format(name, shape)):
        if name == "points":
            api.complete_depth(frame["image"], points=frame["points"], calibration=rig, model=model)
        else:
            api.complete_depth(frame["image"], sparse=frame["sparse"], K=rig.K, model=model)
    if name != "points":
        with pytest.raises(InputError, match=META.format(name, shape)):
            api.check_frame(frame["image"], frame["sparse"], rig.K)
