"""Issue 25, units and geometry through the CLI: ``--sparse-units``, the plausibility of a sparse
PNG against the image and K, K's field of view, an inverted rig transform, one rigid check in
``project`` and ``complete``, binary files as text inputs, and ``project`` pointing clouds and rig
files to ``complete --points --calib``. Each bad input: exit status 2, the first stderr line, nothing
written (oracle: the docs/example rig, whose sparse map has a median of 7.2 m)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from crfdepth.cli import main
from crfdepth.inputs import points_to_sparse
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.kitti import read_depth_png
from crfdepth.io.pointcloud import read_points
from crfdepth.plausibility import check_sparse_plausible

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "example"


@pytest.fixture(scope="module")
def example_sparse() -> np.ndarray:
    """The example scan projected with the example rig: (480, 640) metres."""
    rig = load_any_calibration(EXAMPLE / "rig.yaml")
    return points_to_sparse(read_points(EXAMPLE / "scan.pcd"), rig, (480, 640))


@pytest.fixture()
def frame(tmp_path, example_sparse):
    """Writes the example's sparse map as a PNG in a unit; returns (png, K.txt, out)."""
    K = load_any_calibration(EXAMPLE / "rig.yaml").K
    k_path = tmp_path / "K.txt"
    k_path.write_text(" ".join(f"{v:.6f}" for v in K.ravel()))

    def make(codes_per_metre: float, K_text: str | None = None):
        png = tmp_path / f"sparse_{codes_per_metre:g}.png"
        cv2.imwrite(str(png), np.round(example_sparse * codes_per_metre).astype(np.uint16))
        if K_text is not None:
            k_path.write_text(K_text)
        return png, k_path, tmp_path / "out.png"
    return make


def _refused(capsys, argv, out: Path) -> str:
    assert main(argv) == 2
    first = capsys.readouterr().err.splitlines()[0]
    assert not out.exists()
    return first


def _complete(png, k_path, out, *extra):
    return ["complete", "--image", str(EXAMPLE / "image.png"), "--sparse", str(png), "--intrinsics", str(k_path),
            "--out", str(out), *extra]


def test_millimetre_png_read_as_kitti_is_refused_with_the_option(capsys, frame):
    png, k_path, out = frame(1000.0)
    first = _refused(capsys, _complete(png, k_path, out), out)
    assert first.startswith(f"crfdepth complete: error: --sparse {png}: expected depth in metres (")
    assert "that looks like millimetres: pass --sparse-units mm" in first


def test_plain_metres_png_is_refused_with_the_option(capsys, frame):
    png, k_path, out = frame(1.0)
    first = _refused(capsys, _complete(png, k_path, out), out)
    assert first.startswith(f"crfdepth complete: error: --sparse {png}: expected depth in metres (at most 50% of "
                            f"the returns nearer than 1 m), got 100% of them")
    assert "that looks like whole metres: pass --sparse-units m" in first


def test_sparse_units_read_the_png_in_that_unit(frame, example_sparse):
    """Each unit, read as written, passes the check and gives the metres back within its resolution."""
    K = load_any_calibration(EXAMPLE / "rig.yaml").K
    for units, per_metre in (("kitti", 256.0), ("mm", 1000.0), ("m", 1.0)):
        png, _, _ = frame(per_metre)
        depth = read_depth_png(png, units=units)
        hit = (example_sparse > 0.5 / per_metre) & (example_sparse < 65535 / per_metre)  # uint16 range
        assert np.max(np.abs(depth[hit] - example_sparse[hit])) <= 0.5 / per_metre + 1e-6
        if units != "m":  # whole metres lose the near returns' fraction, still plausible
            check_sparse_plausible("--sparse", depth, K, read_as=units)


def test_sparse_units_with_points_is_refused(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _refused(capsys, ["complete", "--image", str(EXAMPLE / "image.png"), "--points",
                              str(EXAMPLE / "scan.pcd"), "--calib", str(EXAMPLE / "rig.yaml"), "--sparse-units", "mm",
                              "--out", str(out)], out)
    assert first.startswith("crfdepth complete: error: --sparse-units: cannot be combined with --points/--calib")


def test_focal_length_of_4_px_is_refused(capsys, frame):
    png, k_path, out = frame(256.0, "4 0 313.984 0 4 204.336 0 0 1")
    first = _refused(capsys, _complete(png, k_path, out), out)
    assert first.startswith(f"crfdepth complete: error: --intrinsics {k_path}: expected a field of view below 170 "
                            f"degrees over the 640x480 (WxH) image, got 178.6 x 178.0 degrees (fx=4, fy=4 px)")


def test_png_as_intrinsics_is_refused_as_binary(capsys, frame):
    png, _, out = frame(256.0)
    first = _refused(capsys, _complete(png, EXAMPLE / "image.png", out), out)
    assert first == (f"crfdepth complete: error: --intrinsics: expected a text file with 9 numbers (row-major 3x3 "
                     f"K), got a binary file (a PNG image) {EXAMPLE / 'image.png'}")


def test_png_as_calib_is_refused_as_binary(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _refused(capsys, ["complete", "--image", str(EXAMPLE / "image.png"), "--points",
                              str(EXAMPLE / "scan.pcd"), "--calib", str(EXAMPLE / "image.png"), "--out", str(out)], out)
    assert first == (f"crfdepth complete: error: --calib: expected a text file with 'key: values' lines (a KITTI "
                     f"calibration), got a binary file (a PNG image) {EXAMPLE / 'image.png'}")


def _inverted_rig(tmp_path) -> Path:
    data = yaml.safe_load((EXAMPLE / "rig.yaml").read_text())
    data["T_cam_lidar"] = np.linalg.inv(np.array(data["T_cam_lidar"])).round(6).tolist()
    path = tmp_path / "inverted.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_inverted_example_rig_is_refused(capsys, tmp_path):
    rig, out = _inverted_rig(tmp_path), tmp_path / "out.png"
    first = _refused(capsys, ["complete", "--image", str(EXAMPLE / "image.png"), "--points",
                              str(EXAMPLE / "scan.pcd"), "--calib", str(rig), "--out", str(out)], out)
    assert first.startswith(f"crfdepth complete: error: --calib {rig}: expected the transform that maps LiDAR points "
                            f"into the camera frame (x right, y down, z forward), got one that looks inverted: it "
                            f"turns the scan's ground plane 90 degrees from level under the camera, its inverse 1 "
                            f"degrees; invert it in the calibration file, or give --trust-transform to use it as given")
    # and --trust-transform does use it as given
    assert main(["complete", "--image", str(EXAMPLE / "image.png"), "--points", str(EXAMPLE / "scan.pcd"), "--calib",
                 str(rig), "--trust-transform", "--out", str(out), "--quiet"]) == 0
    assert "looks inverted" not in capsys.readouterr().err


def _kitti_calib(tmp_path, Tr: np.ndarray) -> Path:
    P2 = "721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884"
    path = tmp_path / "calib.txt"
    path.write_text(f"P0: {P2}\nP1: {P2}\nP2: {P2}\nP3: {P2}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
                    f"Tr_velo_to_cam: {' '.join(f'{v:g}' for v in Tr[:3].ravel())}\n")
    return path


def _scan(tmp_path) -> Path:
    path = tmp_path / "scan.bin"
    rng = np.random.default_rng(0)
    np.column_stack([rng.uniform(5, 30, 200), rng.uniform(-5, 5, 200), rng.uniform(-1.5, 1, 200),
                     np.zeros(200)]).astype("<f4").tofile(path)
    return path


NON_RIGID = np.array([[0, -1.2, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]])


def test_project_refuses_a_non_rigid_transform_like_complete(capsys, tmp_path):
    calib, out = _kitti_calib(tmp_path, NON_RIGID), tmp_path / "out.png"
    image = tmp_path / "image.png"
    cv2.imwrite(str(image), np.zeros((375, 1242, 3), np.uint8))
    first = _refused(capsys, ["project", "--velodyne", str(_scan(tmp_path)), "--calib", str(calib), "--image",
                              str(image), "--out", str(out)], out)
    expected = f"--calib: key 'Tr_velo_to_cam' in {calib}: expected a rigid transform"
    assert first.startswith(f"crfdepth project: error: {expected}")
    first = _refused(capsys, ["complete", "--image", str(image), "--points", str(_scan(tmp_path)), "--calib",
                              str(calib), "--out", str(out)], out)
    assert first.startswith(f"crfdepth complete: error: {expected}")


def test_project_points_a_pcd_to_complete(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _refused(capsys, ["project", "--velodyne", str(EXAMPLE / "scan.pcd"), "--calib", str(EXAMPLE / "rig.yaml"),
                              "--image", str(EXAMPLE / "image.png"), "--out", str(out)], out)
    assert first == (f"crfdepth project: error: --velodyne: expected a KITTI Velodyne scan (.bin, N x 4 float32), "
                     f"got a .pcd point cloud {EXAMPLE / 'scan.pcd'}; for other point clouds and rig calibrations use "
                     f"crfdepth complete --points CLOUD --calib CALIB")


def test_project_points_a_rig_yaml_to_complete(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _refused(capsys, ["project", "--velodyne", str(_scan(tmp_path)), "--calib", str(EXAMPLE / "rig.yaml"),
                              "--image", str(EXAMPLE / "image.png"), "--out", str(out)], out)
    assert first.startswith(f"crfdepth project: error: --calib: expected a KITTI calibration (object-benchmark file "
                            f"or raw-data day folder), got a rig calibration {EXAMPLE / 'rig.yaml'}; for a rig "
                            f"calibration (K, T_cam_lidar) use crfdepth complete --points CLOUD --calib")


def test_key_listing_skips_comments(capsys, tmp_path):
    """A key-value file that is no KITTI calibration reaches the KITTI reader: the keys listed are keys, not
    comments. A rig YAML under another name is recognised by its content and refused as a rig."""
    other = tmp_path / "calib.txt"
    other.write_text("# Camera calibration of another rig\n# P2 is not here\nfocal: 721.5\ncentre: 609.6 172.9\n")
    out = tmp_path / "out.png"
    argv = ["project", "--velodyne", str(_scan(tmp_path)), "--image", str(EXAMPLE / "image.png"), "--out", str(out)]
    first = _refused(capsys, [*argv, "--calib", str(other)], out)
    assert first == f"crfdepth project: error: --calib: key 'P2' not found in {other} (keys present: centre, focal)"
    assert "#" not in first
    renamed = tmp_path / "rig.txt"
    renamed.write_text((EXAMPLE / "rig.yaml").read_text())
    first = _refused(capsys, [*argv, "--calib", str(renamed)], out)
    assert first.startswith(f"crfdepth project: error: --calib: expected a KITTI calibration (object-benchmark file "
                            f"or raw-data day folder), got a rig calibration {renamed}; ")


def test_inverted_rig_through_a_bag_is_refused(capsys, tmp_path):
    """--bag --calib goes through the same inverted-transform test as --points --calib."""
    from crfdepth.data.example_bag import EXAMPLE_TOPICS, write_example_bag

    bag = tmp_path / "street.bag"
    write_example_bag(bag, frames=1)
    rig, out = _inverted_rig(tmp_path), tmp_path / "depth"
    assert main(["complete", "--bag", str(bag), "--image-topic", EXAMPLE_TOPICS["image"], "--points-topic",
                 EXAMPLE_TOPICS["points"], "--calib", str(rig), "--out-dir", str(out)]) == 2
    first = capsys.readouterr().err.splitlines()[0]
    assert first.startswith("crfdepth complete: error: ")
    assert "looks inverted: it turns the scan's ground plane 90 degrees from level under the camera" in first
    assert "; invert it in the calibration file, or give --trust-transform to use it as given" in first
    assert not out.exists()


@pytest.mark.parametrize("mode", ["--input-dir", "--bag"])
def test_sparse_units_outside_one_frame_mode_is_refused(capsys, tmp_path, mode):
    """Folder mode reads KITTI PNGs and bag mode point clouds: a --sparse-units there would be ignored."""
    source = tmp_path / "in"
    source.mkdir()
    out = tmp_path / "out"
    first = _refused(capsys, ["complete", mode, str(source), "--out-dir", str(out), "--sparse-units", "mm"], out)
    assert first.startswith("crfdepth complete: error: --sparse-units mm: applies to --sparse only; ")


def test_an_explicit_sparse_units_overrules_the_rig_guess(capsys, tmp_path, mast_map):
    """A camera 8 m up a mast: refused by default with the way out, completed with --sparse-units kitti."""
    from crfdepth.io.kitti import write_depth_png

    sparse, K = mast_map
    png, k_path, image = tmp_path / "mast.png", tmp_path / "K.txt", tmp_path / "image.png"
    write_depth_png(png, sparse)
    k_path.write_text(" ".join(f"{v:g}" for v in K.ravel()))
    cv2.imwrite(str(image), np.full((*sparse.shape, 3), 128, np.uint8))
    out = tmp_path / "out.png"
    argv = ["complete", "--image", str(image), "--sparse", str(png), "--intrinsics", str(k_path), "--out", str(out),
            "--quiet"]
    first = _refused(capsys, argv, out)
    assert first.startswith(f"crfdepth complete: error: --sparse {png}: expected depth in metres (the ground at most "
                            f"4 m below the camera")
    assert first.endswith("if the camera really is that high (a mast, a drone), give --sparse-units kitti explicitly")
    assert main([*argv, "--sparse-units", "kitti"]) == 0
    assert read_depth_png(out).shape == sparse.shape
